// A Foxglove WebSocket viewer as a third party writes one: npm's @foxglove/ws-protocol client in
// its default setting (subprotocol FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.websocket.v1")
// over the `ws` package. Run by tests/viz/test_live_view.py:
//   node foxglove_ws_client.cjs URL SECONDS TOPIC...
// Prints one JSON object per line: {"event": "open"}, {"event": "serverInfo", ...},
// {"event": "advertise", "topic", "schemaName", "encoding"} and, for each message on a
// subscribed topic, {"event": "message", "topic", "logTime", "data": base64}. Exits 0 after
// SECONDS (or when its stdin closes), 1 on a connection error or close.
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, seconds, ...topics] = process.argv.slice(2);
const out = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const byChannel = new Map();
const bySubscription = new Map();

client.on("open", () => out({ event: "open", protocol: ws.protocol }));
client.on("serverInfo", (info) => out({ event: "serverInfo", name: info.name }));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    byChannel.set(ch.id, ch);
    out({ event: "advertise", topic: ch.topic, schemaName: ch.schemaName, encoding: ch.encoding,
          schemaEncoding: ch.schemaEncoding, schema: ch.schema });
    if (topics.includes(ch.topic)) {
      bySubscription.set(client.subscribe(ch.id), ch);
    }
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const ch = bySubscription.get(subscriptionId);
  if (ch === undefined) return;
  const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
  out({ event: "message", topic: ch.topic, logTime: String(timestamp),
        data: bytes.toString("base64") });
});
client.on("error", (err) => { out({ event: "error", message: String(err) }); process.exit(1); });
client.on("close", (ev) => { out({ event: "close", code: ev.code }); process.exit(1); });
process.stdin.on("end", () => process.exit(0));
process.stdin.resume();
setTimeout(() => process.exit(0), Number(seconds) * 1000);

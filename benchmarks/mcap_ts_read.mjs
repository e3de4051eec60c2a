// Read a recording with the official TypeScript MCAP library (the indexed reader Foxglove's
// apps use, and the stream reader), as a check by hand that other tools read mcsm files:
//   npm install @mcap/core@2 @mcap/nodejs @foxglove/wasm-lz4 @foxglove/wasm-zstd
//   (in that directory) cp .../benchmarks/mcap_ts_read.mjs . && node mcap_ts_read.mjs FILE.mcap
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { open, readFile } from "node:fs/promises";
import decompressLZ4 from "@foxglove/wasm-lz4";
import zstdPkg from "@foxglove/wasm-zstd";
const { isLoaded: zstdLoaded, decompress: decompressZstd } = zstdPkg;
await decompressLZ4.isLoaded;
await zstdLoaded;
const decompressHandlers = {
  lz4: (buf, size) => decompressLZ4(buf, Number(size)),
  zstd: (buf, size) => decompressZstd(buf, Number(size)),
};
const path = process.argv[2];
const fh = await open(path, "r");
let indexed = 0;
try {
  const reader = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(fh), decompressHandlers });
  for await (const m of reader.readMessages()) indexed++;
  console.log(`indexed reader: ${indexed} messages, ${reader.chunkIndexes.length} chunk indexes, ${reader.schemasById.size} schemas`);
} catch (e) { console.log(`indexed reader: error ${e.message}`); }
await fh.close();
const sr = new McapStreamReader({ decompressHandlers, validateCrcs: true });
sr.append(await readFile(path));
let streamed = 0, rec;
try { while ((rec = sr.nextRecord())) if (rec.type === "Message") streamed++; } catch (e) { console.log(`stream error ${e.message}`); }
console.log(`stream reader: ${streamed} messages, done=${sr.done()}`);

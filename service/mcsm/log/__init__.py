"""The recording layer: a map's inputs written to MCAP, read back, replayed and recovered.

Above :mod:`mcsm.map` and below the server and :mod:`mcsm.viz`. The modules, each importing
only those before it:

- :mod:`~mcsm.log.topics`: the topics, schemas, layouts and format versions of a recording,
  :class:`~mcsm.log.topics.RecordingError`, :func:`~mcsm.log.topics.decode_input`;
- :mod:`~mcsm.log.filetype`: whether an MCAP file is an mcsm recording at all;
- :mod:`~mcsm.log.progress`: progress over the bytes read;
- :mod:`~mcsm.log.snapchunks`: snapshots of any size as bounded records;
- :mod:`~mcsm.log.chunkwriter`: the MCAP bytes as written (one chunk per input);
- :mod:`~mcsm.log.writer`: :class:`~mcsm.log.writer.Recorder`;
- :mod:`~mcsm.log.reader`: :class:`~mcsm.log.reader.RecordingReader`, intact chunks of a
  damaged file;
- :mod:`~mcsm.log.recset`: the files of a split recording, in set order;
- :mod:`~mcsm.log.replay`: :func:`~mcsm.log.replay.replay`, deterministic, checking digests;
- :mod:`~mcsm.log.recover`: :func:`~mcsm.log.recover.recover`, a clean copy of a cut file.

The package imports :mod:`mcsm.map`, :mod:`mcsm.wire`, :mod:`mcsm.core`, :mod:`mcsm.errors`
(and ``mcsm.__version__``), never the server, replication, :mod:`mcsm.viz` or the CLI.
This file imports nothing: ``from mcsm.log.replay import replay`` loads what replay needs.
"""

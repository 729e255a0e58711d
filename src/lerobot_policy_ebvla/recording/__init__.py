"""Recording scripted experts as LeRobotDatasets: one loop, one expert per simulator.

- `recording.loop`: the loop every recorder runs (attempt, keep or drop, report).
- `recording.metaworld`: MetaWorld's scripted experts (`RecordMetaworldConfig`, `record_metaworld`).
- `recording.libero`: a scripted LIBERO-Object expert (`RecordLiberoConfig`, `record_libero`); needs the
  `libero` extra only when it records.
"""

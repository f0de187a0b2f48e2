"""Files (docs/architecture.md: hostlink/files): one reader and one writer for each file the host handles, and the one
time module.

``session`` (session files, CSV or Parquet, read whole or in chunks of whole frames), ``columnar`` (the Parquet
schema and its pyarrow side), ``params`` (camera parameter files; the package's own by name, ``builtin:NAME``),
``truth`` (simulation truth JSON), ``trace`` (replay trace CSV, written as the replay goes), ``attitude`` (attitude
CSV), ``times`` (ISO 8601 UTC, two-part Julian dates, wire microseconds; UTC -> TT / UT1), ``atomic`` (the one
atomic writer every file goes through) and ``cache`` (the project's user cache directory, for every cache).
"""

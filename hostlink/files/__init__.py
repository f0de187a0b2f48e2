"""Files (ARCHITECTURE.md: hostlink/files): one reader and one writer for each file the host handles, and the one
time module.

``session`` (session CSV), ``params`` (camera parameter files; the package's own by name, ``builtin:NAME``),
``truth`` (simulation truth JSON), ``trace`` (replay trace CSV), ``attitude`` (attitude CSV), ``times`` (ISO 8601
UTC, two-part Julian dates, wire microseconds; UTC -> TT / UT1) and ``atomic`` (the one atomic writer every file goes
through).
"""

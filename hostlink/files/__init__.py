"""Files (ARCHITECTURE.md: hostlink/files): sessions, parameter files, truth files, traces, and time stamps; one
reader and one writer for each, every write atomic."""

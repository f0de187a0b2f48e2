"""Message formats shared by sensor and host (docs/architecture.md): messages, codecs, framing, CRC, parameter table,
DBC and Modbus map. Bytes in, messages out: no I/O, imports neither ``onboard`` nor ``hostlink``."""

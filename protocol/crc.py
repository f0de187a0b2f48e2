"""Checksums used on the wire: CRC-32 (IEEE 802.3, as zlib.crc32) for serial frames and parameter sets, and
CRC-16/CCITT (binascii.crc_hqx, initial value 0xFFFF) where a 16-bit field is all a message has room for.

Both are table-driven, standard, and implemented in C by the Python standard library; a C port of the firmware
uses the same polynomials (0x04C11DB7 reflected, 0x1021), so checksums computed on either side match.
"""

from __future__ import annotations

import binascii
import zlib


def crc32(data: bytes | bytearray | memoryview) -> int:
    """CRC-32/ISO-HDLC of ``data`` (check value of b"123456789" is 0xCBF43926)."""
    return zlib.crc32(data) & 0xFFFFFFFF


def crc16_ccitt(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value of b"123456789" is 0x29B1)."""
    return binascii.crc_hqx(bytes(data), 0xFFFF)

"""The emulated sensor (docs/architecture.md): the real ``onboard`` firmware logic behind a real link endpoint.

``hostlink emulate --transport T`` builds an :class:`~hostlink.emulator.sensor.EmulatedSensor` (firmware + frame
source) and hands it to the endpoint module ``ENDPOINTS[T]``, whose ``serve(sensor, options, ready, stop)`` opens the
endpoint (pty, CAN hub, Modbus server), reports the link string through ``ready``, and serves until ``stop`` is set.
See hostlink/links/INTERFACE.md. The sensor's parameter banks live in RAM, or with ``--flash FILE`` in a NOR-flash
image file (``flash.py``: the file I/O; the record layout and recovery are ``onboard.banks``).
"""

from __future__ import annotations

#: --transport value -> endpoint module (imported on use).
ENDPOINTS: dict[str, str] = {
    "serial": "hostlink.emulator.serial_endpoint",
    "can": "hostlink.emulator.can_endpoint",
    "modbus": "hostlink.emulator.modbus_endpoint",
}

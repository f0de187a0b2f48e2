"""The port kit (ARCHITECTURE.md: hostlink/portkit): what a firmware engineer needs to port the sensor to C.

- :mod:`hostlink.portkit.export_c`: C99 headers and one C source generated from the single protocol definition
  (``protocol.messages.MESSAGES``, ``protocol.framing``, ``protocol.param_table``, ``protocol.can_frames``).
- :mod:`hostlink.portkit.vectors`: golden test vectors from the onboard reference model, float32 and fixed point,
  each with the tolerance a port must meet and why.
- :mod:`hostlink.portkit.costs`: operations and memory per function and per frame, for budgeting a microcontroller.
- :mod:`hostlink.portkit.firmware_c`: the C firmware core (``onboard/c``) built with the machine's compiler and run
  behind the Python firmware's interface (``hostlink emulate --firmware c``).

docs/port-kit.md is the user's guide.
"""

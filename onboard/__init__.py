"""The sensor's reference model (docs/architecture.md): camera model, recursive calibration, refraction, apparent place,
attitude, parameter banks and the firmware state machine. numpy only, explicit dtypes (float32 or fixed point),
no I/O, no clock: time comes in with the data. A C port should be a translation, not a redesign."""

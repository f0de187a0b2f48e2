"""pyserial URL handlers of the host (``serial.protocol_handler_packages`` entry): ``bufsocket://HOST:PORT``."""

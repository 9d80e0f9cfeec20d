"""The wire: how rosgate's bytes look on a link. No rclpy, no sockets, no plugins.

* :mod:`.envelope` — the 28-byte header in front of every frame, and the replay window.
* :mod:`.framing` — length prefixes on streams; fragments and compact pieces on datagram links
  (putting them back together is :mod:`rosgate.reassembly`'s).
* :mod:`.serial_datagram` — the SLIP-style framing (with CRC-32) of the CVRA microcontroller
  profile's service calls.
* :mod:`.names` — a name in front of a bare datagram, as the CVRA profile writes it.
* :mod:`.control` — the main line's control messages (JSON), read within bounds.

Everything here decodes bytes from the network: it raises its own error types (or reports
through a callback), never anything else, and holds bounded memory.
"""

"""The wire: how rosgate's bytes look on a link. No rclpy, no sockets, no plugins.

* :mod:`.envelope` — the 28-byte header in front of every frame, and the replay window.
* :mod:`.framing` — length prefixes on streams; batches and fragments on datagram links
  (fragments cut and put back together by the packetizer of :mod:`rosgate.builtin`).
* :mod:`.names` — a name in front of a bare datagram, as the CVRA profile writes it.
* :mod:`.control` — the main line's control messages (JSON), read within bounds.

Everything here decodes bytes from the network: it raises its own error types (or reports
through a callback), never anything else, and holds bounded memory.
"""

"""The wire: how rosgate's bytes look on a link (:mod:`.envelope`, :mod:`.framing`, :mod:`.names`,
:mod:`.control`). No rclpy, no sockets, no plugins. Everything here decodes bytes from the
network: it raises its own error types, never anything else, and holds bounded memory.
"""

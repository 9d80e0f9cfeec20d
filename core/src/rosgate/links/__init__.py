"""Links: the core's side of a transport — a queue, threads and dispatch — so a transport
plugin only opens sockets. :mod:`.base` is what a route sends through (:class:`~.base.Link`,
:class:`~.base.Sender`, the counters); :mod:`.datagram` a datagram link's every frame, out and
in (and the send turn stream links share); :mod:`.datagram_base` what a datagram link does
beside its frames (construction, packetizers, timers, the line watch, the send thread);
:mod:`.sending` the queue and threads of both kinds; :mod:`.lifetime` what a bridge closes when
it stops. Stream links are :mod:`rosgate.streamlink`'s.
"""

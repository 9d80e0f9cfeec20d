"""Stream links: one connection as a link, its records written and read (:mod:`.link`), the slot
a route sends through while connections come and go (:mod:`.slot`), and the connector that
keeps it filled (:mod:`.connector`).
"""

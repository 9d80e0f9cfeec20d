"""Resolving: a bringup.yaml's entries, checked against the installed plugins, become a plan of
route specs without opening anything (all ``rosgate check`` needs); a server resolves a client's
hello the same way, with an error maker that names the client. :mod:`.plan` is the whole plan,
:mod:`.entries` one entry, :mod:`.places` where its frames go, :mod:`.made` its plugins.
"""

"""One client connection, whatever the transport (:mod:`.session`): its input with the realtime
path and the bounded line queue (:mod:`.input`, :mod:`.backlog`), its output with one reply
per line, status reports and pushes (:mod:`.output`, :mod:`.outbox`), and logging in
(:mod:`.login_guard`).

May import: ``kernel`` and everything below it. Never transports, the API or the app."""

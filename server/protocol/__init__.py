"""The Grbl/Smoothie line protocol, sans-I/O: bytes in, lines and realtime events out, replies
and reports formatted. One instance per connection; no I/O."""

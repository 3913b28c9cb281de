"""Messaging: the Zenoh session helpers, the wire format and the key expressions."""

"""Keys and trust: `crypto` (X25519 sessions, ChaCha20-Poly1305, the input tag),
`identity` (Ed25519 identity keys, signed texts), `trust` (which identities
a participant or a core accepts: pins and anchors)."""

__all__: list[str] = []

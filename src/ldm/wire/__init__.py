"""The LDM's wire: every topic (`topics`: the builders and the one `topics.parse`),
every message (`messages`: pydantic models, encoded once at the edge), the rotation
policy a grant carries (`rotation`), and the AsyncAPI document drawn from both
(`asyncapi`). Nothing else in the LDM spells a topic or a
payload."""

__all__: list[str] = []

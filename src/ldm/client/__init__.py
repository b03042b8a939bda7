"""The participant's side: `participant` (`Participant` and its `Session`s: discovery,
pinned keys, encrypted requests) and `routing` (a `RoutedSession` that sends each input
to the provider whose coverage holds it)."""

__all__: list[str] = []

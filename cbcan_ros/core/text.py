"""Text for messages: input is echoed back cut short, never whole."""


def quoted(text: str, limit: int = 32) -> str:
    """Return ``text`` quoted and cut to ``limit`` characters: never echo unbounded input."""
    return repr(text[:limit]) + ('...' if len(text) > limit else '')

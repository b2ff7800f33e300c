"""Text for messages: input is echoed back cut short, never whole; words every service uses."""

# Why a request was refused or not finished: the gateway is stopping (every service says so
# alike, so a caller can tell it from a fault).
SHUTTING_DOWN = 'the gateway is shutting down'


def quoted(value, limit: int = 32) -> str:
    """Return ``value`` as a message shows it (its repr) cut to ``limit``: never echo it whole.

    A string is cut before quoting, so the quotes stay and ``...`` says it went on.
    """
    if isinstance(value, str):
        return repr(value[:limit]) + ('...' if len(value) > limit else '')
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + '...'

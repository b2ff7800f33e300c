"""Text for messages: input is echoed back cut short, never whole; words every service uses."""

# Why a request was refused or not finished: the gateway is stopping (every service says so
# alike, so a caller can tell it from a fault).
SHUTTING_DOWN = 'the gateway is shutting down'
# Why nothing but a stop goes out now: the gateway was held up longer than its drives watch
# its heartbeat (said once, when it goes on; a refusal of it is no drive's fault).
HEARTBEAT_SILENT = 'the heartbeat of the gateway has been silent'


def quoted(value, limit: int = 32) -> str:
    """Return ``value`` as a message shows it (its repr) cut to ``limit``: never echo it whole.

    A string is cut before quoting, so the quotes stay and ``...`` says it went on.
    """
    if isinstance(value, str):
        return repr(value[:limit]) + ('...' if len(value) > limit else '')
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + '...'

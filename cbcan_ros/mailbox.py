"""PLC register mailboxes (placeholder until the translators land)."""


class Mailbox:
    """Executes PLC register blocks on the gateway."""

    def __init__(self, gateway, completion):
        self._gateway = gateway
        self._completion = completion

    async def execute(self, block_format: str, registers):
        """Execute one register block; return (registers, message)."""
        return registers, f'format {block_format!r} is not implemented yet'

"""The PLC register mailboxes, translated onto the core."""

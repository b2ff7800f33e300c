"""Boot configuration: every device checked, configured, started each time it boots (CiA 302-2)."""

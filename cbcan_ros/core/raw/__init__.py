"""Raw CAN frames: any frame published, frames sent by programs within the send rules.

Entry point: ``frames.RawFrames``; ``filters`` parses and applies candump-style filters.
"""

"""Phase-retrieval engines: iteration only, no I/O, progress through callbacks."""

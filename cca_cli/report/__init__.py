"""Numbers (JSON) and figures (PNG) people look at."""

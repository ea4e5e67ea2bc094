"""The command-line surface: argument parsing, rich output and exit codes (no math)."""

"""``python -m cca_cli`` runs the command-line interface."""

from cca_cli.commands.entry import main

main()

"""``python -m rflscm.cli`` runs the command line."""

from rflscm.cli import main

main()

"""``python -m ohmni_tb`` runs the ``ohmni`` command line."""

from __future__ import annotations

from ohmni_tb.cli import main

if __name__ == "__main__":
    main()

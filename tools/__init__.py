"""Research tooling run from the repository root (``python -m tools...``); not part of the installed package."""

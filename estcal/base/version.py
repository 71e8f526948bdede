"""The version of estcal (written into saved models and reports; ``pyproject.toml`` holds the same)."""
__version__ = "0.1.0"

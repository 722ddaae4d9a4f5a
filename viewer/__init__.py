"""The validation web viewer (viser)."""

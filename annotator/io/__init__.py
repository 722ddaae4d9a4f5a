"""Input/output at the edges: atomic file writes and image files."""

"""Fiducial markers on parts: where they go (layout), what they look like (texture), and what
a user prints (sheets) or inspects (textured mesh)."""

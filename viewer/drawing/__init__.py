"""The review's pictures, pixel-exact, made on the server from a scene's prepared overlays."""

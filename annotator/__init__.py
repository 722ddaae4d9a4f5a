"""Ground-truth 6D poses for bin-picking scenes."""

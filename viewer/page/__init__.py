"""One browser page of the review: its cursor, panel, pictures, canvas and repairs."""

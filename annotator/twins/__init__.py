"""Synthetic twins of annotated scenes (paper section 5): rendering them
(:mod:`.render`) and comparing them with the real captures (:mod:`.report`)."""

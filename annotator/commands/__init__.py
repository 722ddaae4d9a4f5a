"""One module per ``annotator`` subcommand: argument parsing and terminal output only.

The work itself lives in the pipeline packages; a command module wires options to library
calls and prints results (``--json`` where scripts consume the output).
"""

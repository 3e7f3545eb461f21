"""``python -m experiments``: the command-line runner of jaxedit."""

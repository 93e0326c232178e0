"""Sub-command groups of the ``dslrxr`` command, one module per pipeline area.

Each module exposes ``register(app)``, adds its commands to the Typer app and imports the
core lazily inside the commands so ``dslrxr --help`` stays fast.
"""

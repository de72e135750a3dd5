"""`python -m pipeline.cli`: the `needlecue` console script without installing it."""

from pipeline.cli import app

app()

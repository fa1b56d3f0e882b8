"""``python -m scenes.app.cli``: the ``newtsim`` command."""

from . import main

main()

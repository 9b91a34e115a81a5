"""``python -m plenoptrack``: the same as the ``plenoptrack`` command."""

from .cli import main

main()

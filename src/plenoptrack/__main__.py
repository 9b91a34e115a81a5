"""``python -m plenoptrack``: the same as the ``plenoptrack`` command."""

from .cli import main

if __name__ == "__main__":
    main()

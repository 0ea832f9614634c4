"""``python -m ndtom_ti``: the ``ndtom`` command."""

from ndtom_ti.cli import main

if __name__ == "__main__":
    main()

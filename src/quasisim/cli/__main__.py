"""``python -m quasisim.cli``."""

from quasisim.cli import main

if __name__ == "__main__":  # pragma: no cover
    main()

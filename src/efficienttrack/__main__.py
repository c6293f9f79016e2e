"""``python -m efficienttrack``: the command line, as the ``efficienttrack`` console script."""

from efficienttrack.cli import main

if __name__ == "__main__":
    main()

"""``python -m efficienttrack`` and the ``efficienttrack`` console script: the command line."""

from efficienttrack.cli import main

if __name__ == "__main__":
    main()

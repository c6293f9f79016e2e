"""``python -m efficienttrack``: the command line, as the ``efficienttrack`` console script."""

from efficienttrack.cli import main

main()

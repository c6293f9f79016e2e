"""``python -m efficienttrack`` and the ``efficienttrack`` console script: the command line.

On the torch-free runtime install (docs/deploy.md: the package with ``--no-deps`` and the ``runtime`` extra) the
command line's libraries are absent; :func:`main` then says so in one line instead of a traceback.
"""

import sys

FULL_INSTALL = ("typer", "torch", "matplotlib", "scipy", "gymnasium", "stable_baselines3", "ray", "tensorboard", "onnx")
"""Libraries of the full install that the command line imports and the torch-free runtime install leaves out."""


def main() -> None:
    """Run the command line; exit 2 with one line when a library of the full install is missing."""
    try:
        from efficienttrack.cli import main as command_line
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in FULL_INSTALL:
            raise
        sys.stderr.write(
            f"error: the efficienttrack command line needs the full install ({exc.name} is missing): pip install "
            "efficienttrack with its dependencies; on the torch-free runtime install, deploy from Python with "
            "efficienttrack.deploy.onnx_runtime (docs/deploy.md)\n"
        )
        sys.exit(2)
    command_line()


if __name__ == "__main__":
    main()

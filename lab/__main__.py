"""``python -m lab``: the same as the ``vision-lab`` command."""

from lab.cli import app

if __name__ == "__main__":
    app(prog_name="vision-lab")

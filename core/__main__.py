"""``python -m calib``: the same as the ``calib`` command."""
from calib.cli.entry import main

if __name__ == "__main__":
    main()

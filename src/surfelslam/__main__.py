"""``python -m surfelslam``: the same as the ``surfelslam`` command."""

from surfelslam.cli import main

if __name__ == "__main__":
    main()

"""Write the configuration reference, ``docs/config_reference.md``, from the settings' metadata (``make docs``).

``python -m surfelslam.tools.gen_docs [PATH]`` writes the page atomically and prints nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path

DEFAULT_PATH = Path("docs") / "config_reference.md"


def reference_text() -> str:
    """The page's text: :func:`~surfelslam.config_reference.reference_markdown` of ``SlamConfig``."""
    from surfelslam.config_reference import reference_markdown
    from surfelslam.slam.config import SlamConfig

    return reference_markdown(SlamConfig)


def main(argv: list[str] | None = None) -> None:
    from surfelslam.io.atomic import write_text_atomic

    args = sys.argv[1:] if argv is None else argv
    write_text_atomic(Path(args[0]) if args else DEFAULT_PATH, reference_text())


if __name__ == "__main__":
    main()

"""Write the OpenAPI document the app serves: ``python -m service.openapi [PATH]``.

Default path: ``openapi/openapi.json`` (committed; a test checks it matches the app).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

DEFAULT_PATH = Path("openapi/openapi.json")


def document() -> str:
    """The app's OpenAPI document as stable, indented JSON (with a final newline)."""
    from .app import create_app
    from .settings import Settings

    return json.dumps(create_app(Settings()).openapi(), indent=2, sort_keys=False) + "\n"


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(document())
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

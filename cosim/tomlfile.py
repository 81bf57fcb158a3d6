"""Reading the TOML files a user hands MineTwin (scenarios, DEM and server configs).

Every way a file can be wrong (missing, a folder, not UTF-8, not TOML) is a
``ValidationError`` naming the field that pointed at it and the file.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from cosim.errors import ValidationError


def read_toml(path, field: str = "config") -> dict:
    """The TOML document at ``path``; ``field`` names the argument or key that gave it."""
    path = Path(path)
    if path.is_dir():
        raise ValidationError(field, "a TOML file", f"{str(path)!r} is a folder")
    if not path.is_file():
        raise ValidationError(field, "an existing TOML file", f"{str(path)!r} not found")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise ValidationError(field, "a UTF-8 text file (TOML)",
                              f"{path}: byte {exc.start} is not UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValidationError(field, "valid TOML", f"{path}: {exc}") from None

"""AP path-loss models beside a radio map: JSON, written atomically, checked on load.

The file carries ``content_sha256`` (SHA-256 of its canonical JSON without that key), so a
changed byte is an error, and ``radio_map_sha256`` (``radiomap_io.content_hash`` of the map
the models were fitted from), so models of another (e.g. an earlier survey's) map are never
used for this one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any

from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.tracking.apmodel import ApFitConfig, ApModels
from graphslam.errors import GraphSlamError, InputError
from graphslam.io.atomic import atomic_write_text, json_safe

HASH_KEY = "content_sha256"
RADIO_MAP_KEY = "radio_map_sha256"
FIT_KEY = "fit"  # the ApFitConfig the models were fitted with (a later survey refits with it)


class StaleApModelsError(InputError):
    """The AP models were fitted to another radio map than the one they are used with."""


def _digest(doc: dict[str, Any]) -> str:
    canonical = json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    return hashlib.sha256(canonical.encode()).hexdigest()


def write_ap_models(
    models: ApModels, path: str | Path, *, radio_map: RadioMap | None = None, fit: ApFitConfig | None = None
) -> Path:
    """JSON, written atomically (the file is complete or absent). ``radio_map``: the map the
    models were fitted from (recorded, so that ``read_ap_models`` can refuse another map's);
    ``fit``: the settings they were fitted with (recorded, ``read_fit_config``)."""
    from graphslam.io.radiomap_io import content_hash

    doc: dict[str, Any] = json_safe(models.as_dict())  # type: ignore[assignment]
    if radio_map is not None:
        doc[RADIO_MAP_KEY] = content_hash(radio_map)
    if fit is not None:
        doc[FIT_KEY] = json_safe(dataclasses.asdict(fit))
    doc[HASH_KEY] = _digest(doc)
    atomic_write_text(path, json.dumps(doc, indent=2, allow_nan=False))
    return Path(path)


def read_ap_models(path: str | Path, *, radio_map: RadioMap | None = None) -> ApModels:
    """Read AP models; ``InputError`` if unreadable, malformed or damaged (content hash), and
    ``StaleApModelsError`` if ``radio_map`` is given and is not the map they were fitted from."""
    from graphslam.io.radiomap_io import content_hash

    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as e:
        raise InputError(path, f"cannot read AP models: {' '.join(str(e).split())}") from None
    if not isinstance(d, dict):
        raise InputError(path, "malformed AP models (not a JSON object)")
    stored = d.pop(HASH_KEY, None)
    if stored is None:
        raise InputError(
            path, "no content hash (written by an older graphslam?): re-run `graphslam fit-aps`", field=HASH_KEY
        )
    try:
        ok = stored == _digest(d)
    except ValueError:  # NaN/inf literals: never written by write_ap_models
        ok = False
    if not ok:
        raise InputError(path, "content does not match its SHA-256: the file is damaged or was edited", field=HASH_KEY)
    if radio_map is not None:
        fitted_to, this = d.get(RADIO_MAP_KEY), content_hash(radio_map)
        if fitted_to != this:
            raise StaleApModelsError(
                path,
                f"fitted to another radio map ({str(fitted_to)[:12]}..., this one is {this[:12]}...): "
                "re-run `graphslam fit-aps` on this map",
                field=RADIO_MAP_KEY,
            )
    try:
        return ApModels.from_dict(d)
    except (KeyError, TypeError, ValueError, GraphSlamError) as e:
        raise InputError(path, f"malformed AP models ({type(e).__name__}: {e})") from None


def read_fit_config(path: str | Path) -> ApFitConfig:
    """The fit settings an AP models file records (``write_ap_models(fit=...)``); the defaults when
    it records none (checked and read as ``read_ap_models`` does)."""
    read_ap_models(path)  # damaged or malformed: InputError
    d = json.loads(Path(path).read_text(encoding="utf-8")).get(FIT_KEY)
    if not isinstance(d, dict):
        return ApFitConfig()
    try:
        return ApFitConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
    except (TypeError, ValueError, GraphSlamError) as e:
        raise InputError(path, f"malformed fit settings: {e}", field=FIT_KEY) from None

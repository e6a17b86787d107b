"""Asset ids, collision checks and split lists for imported meshes (``physgm.data.from_meshes``).

An id is the mesh's path relative to the folder it was found in, suffix dropped, folders joined
by ``__``; files whose ids would coincide get a hash suffix, and a folder already holding another
mesh under that id is an error, so two objects never become one asset (docs/data.md, "Meshes").
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path

from physgm.data.format import SPLITS, SPLITS_DIR

MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".ply", ".stl", ".off")


@dataclass(frozen=True)
class MeshFile:
    """A mesh file and the folder it was found under (ids are relative to that folder)."""

    path: Path
    root: Path

    @property
    def relative(self) -> str:
        return self.path.relative_to(self.root).as_posix()


def asset_id_for(path: Path, root: Path | None = None) -> str:
    """The id of a mesh file: its path relative to ``root`` (default: its folder), suffix dropped."""
    rel = path.relative_to(root if root is not None else path.parent).with_suffix("")
    return "__".join(re.sub(r"[^A-Za-z0-9_.-]+", "_", part) for part in rel.parts)


def _digest(text: str) -> str:
    return hashlib.sha1(text.encode()).hexdigest()[:8]


def assign_ids(meshes: list[MeshFile]) -> dict[Path, str]:
    """Unique asset ids for ``meshes``; files whose plain ids coincide get a hash suffix.

    The suffix hashes the relative path with its extension (stable when the folder moves); for
    the same relative path under two folders, the folder name is hashed too, then the full path.
    """
    groups: dict[str, list[MeshFile]] = {}
    for m in meshes:
        groups.setdefault(asset_id_for(m.path, m.root), []).append(m)
    ids: dict[Path, str] = {}
    for base, members in groups.items():
        if len(members) == 1:
            ids[members[0].path] = base
            continue
        for key in (
            lambda m: m.relative,
            lambda m: f"{m.root.resolve().name}/{m.relative}",
            lambda m: m.path.resolve().as_posix(),
        ):
            renamed = {m.path: f"{base}-{_digest(key(m))}" for m in members}
            if len(set(renamed.values())) == len(members):
                break
        ids.update(renamed)
    seen: dict[str, Path] = {}
    for path, aid in ids.items():
        if aid in seen:
            raise ValueError(
                f"asset id {aid!r} would name both {seen[aid]} and {path}; rename one of the files"
            )
        seen[aid] = path
    return ids


def file_sha1(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha1").hexdigest()


def existing_import(out: Path, aid: str, mesh: Path, digest: str) -> bool:
    """True if ``out/aid`` already holds this mesh; raises if it holds a different one."""
    folder = out / aid
    if not folder.is_dir():
        return False
    try:
        physical = json.loads((folder / "physical.json").read_text())
    except (OSError, ValueError):
        physical = {}
    if physical.get("mesh_sha1") == digest:
        return True
    held = physical.get("mesh_file", "an unknown source")
    raise ValueError(
        f"asset id {aid!r} already exists in {out} and was imported from {held}, not from {mesh}; "
        "import into another --out folder or remove the old asset"
    )


def find_meshes(items: list[str]) -> list[MeshFile]:
    """Mesh files of the given files and folders (searched recursively), each with its id root."""
    files: list[MeshFile] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            files += [MeshFile(f, p) for f in sorted(p.rglob("*")) if f.suffix.lower() in MESH_SUFFIXES]
        elif p.is_file():
            files.append(MeshFile(p, p.parent))
        else:
            raise FileNotFoundError(f"no mesh file or folder at {p}")
    first: dict[Path, MeshFile] = {}
    for m in files:  # a file named twice (on its own and inside a folder) is imported once
        first.setdefault(m.path.resolve(), m)
    return list(first.values())


def _split_ids(path: Path) -> list[str]:
    return [ln.split("#")[0].strip() for ln in path.read_text().splitlines() if ln.split("#")[0].strip()]


def add_to_split(out: Path, split: str, ids: list[str]) -> None:
    """Append ids to ``splits/<split>.txt`` (each id once) and make sure every split file exists.

    Raises ValueError, writing nothing, if an id is already listed in another split.
    """
    (out / SPLITS_DIR).mkdir(parents=True, exist_ok=True)
    for s in SPLITS:
        (out / SPLITS_DIR / f"{s}.txt").touch()
    elsewhere = {
        i: s for s in SPLITS if s != split for i in _split_ids(out / SPLITS_DIR / f"{s}.txt") if i in ids
    }
    if elsewhere:
        listing = ", ".join(f"{i} ({s})" for i, s in sorted(elsewhere.items())[:5])
        raise ValueError(f"already in another split: {listing}; an asset belongs to one split only")
    path = out / SPLITS_DIR / f"{split}.txt"
    have = list(dict.fromkeys(_split_ids(path)))
    path.write_text("".join(f"{a}\n" for a in have + [i for i in dict.fromkeys(ids) if i not in have]))


def count_assets(out: Path) -> int:
    """Asset folders in ``out`` (splits and unfinished temporary folders excluded)."""
    return sum(1 for p in out.iterdir() if p.is_dir() and p.name != SPLITS_DIR and not p.name.startswith("."))

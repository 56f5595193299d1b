"""The project file: one SQLite database (`*.tracemap`) holding everything a user made.

Schema versioned by `PRAGMA user_version`, WAL journal, one transaction per edit, so a crash or a killed
process loses nothing that was committed and never leaves half an edit. The mesh and the photos are
referenced by path (relative to the project), size and SHA-256; a moved or changed file is reported, never
silently used. Arrays are stored as `.npy` blobs. One process at a time holds a project (an advisory lock
on `<project>.lock`).
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import io
import json
import math
import os
import re
import sqlite3
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from engine.cameras import Camera, check_cameras_see, check_images, read_cameras
from engine.cameras.detect import detect_format
from engine.errors import InputError, ProjectError
from engine.io import jsonable
from engine.mesh import Mesh, read_mesh
from engine.register import Registration
from engine.scan_circle import ScanCircle
from engine.scanline import Scanline
from engine.sets import Facet
from engine.traces import Trace2D, Trace3D, traces_digest

SCHEMA_VERSION = 5
SUFFIX = ".tracemap"
# what each stored result depends on besides the traces' ids and vertices (`traces_digest`)
RESULT_BASIS = {"sets": ("normal", "set_id", "kind"), "density_peaks": ("normal", "kind"),
                "topology": ("term_start", "term_end", "kind"), "lengths": ("set_id", "term_start", "term_end", "kind"),
                "intensity": ("set_id", "kind")}

_FACETS = """
CREATE TABLE facets (id INTEGER PRIMARY KEY AUTOINCREMENT, centroid BLOB NOT NULL, normal BLOB NOT NULL,
                     planarity REAL NOT NULL, rms REAL NOT NULL, n_points INTEGER NOT NULL, radius REAL NOT NULL,
                     faces BLOB NOT NULL, rejected_reason TEXT NOT NULL DEFAULT '');
"""
_SCANLINES = """
CREATE TABLE scanlines (id INTEGER PRIMARY KEY AUTOINCREMENT, name TEXT NOT NULL DEFAULT '',
                        start_point BLOB NOT NULL, end_point BLOB NOT NULL, reach REAL NOT NULL);
"""
_SCAN_CIRCLES = """
CREATE TABLE scan_circles (id INTEGER PRIMARY KEY AUTOINCREMENT, name TEXT NOT NULL DEFAULT '',
                           centre BLOB NOT NULL, radius REAL NOT NULL);
"""
_KINDS = """
ALTER TABLE traces2d ADD COLUMN kind TEXT NOT NULL DEFAULT 'fracture';
ALTER TABLE traces3d ADD COLUMN kind TEXT NOT NULL DEFAULT 'fracture';
"""
_SCHEMA_V1 = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE inputs (role TEXT PRIMARY KEY, path TEXT NOT NULL, size INTEGER NOT NULL,
                     mtime REAL NOT NULL, sha256 TEXT NOT NULL);
CREATE TABLE images (name TEXT PRIMARY KEY, camera TEXT NOT NULL, path TEXT, size INTEGER,
                     mtime REAL, sha256 TEXT);
CREATE TABLE traces2d (id INTEGER PRIMARY KEY AUTOINCREMENT,
                       image TEXT NOT NULL REFERENCES images(name), polyline BLOB NOT NULL,
                       source TEXT NOT NULL CHECK (source IN ('manual', 'auto')),
                       component INTEGER NOT NULL DEFAULT -1);
CREATE TABLE traces3d (id INTEGER PRIMARY KEY AUTOINCREMENT, points BLOB NOT NULL, uv BLOB NOT NULL,
                       face BLOB NOT NULL, image_index BLOB NOT NULL, images TEXT NOT NULL,
                       parents TEXT NOT NULL, component INTEGER NOT NULL DEFAULT -1, normal BLOB,
                       method TEXT NOT NULL DEFAULT '', K REAL, M REAL, dispersion REAL,
                       set_id INTEGER NOT NULL DEFAULT -1, term_start TEXT NOT NULL DEFAULT '',
                       term_end TEXT NOT NULL DEFAULT '', extra TEXT NOT NULL DEFAULT '{}');
CREATE TABLE maps (name TEXT PRIMARY KEY, vertex_values BLOB NOT NULL, info TEXT NOT NULL);
CREATE TABLE results (name TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE gcps (name TEXT PRIMARY KEY, world TEXT NOT NULL, observations TEXT NOT NULL);
CREATE INDEX traces2d_image ON traces2d(image);
"""
# Schema upgrades: MIGRATIONS[v] turns a version-v file into version v + 1 (statements separated by ';').
MIGRATIONS: dict[int, str] = {1: _FACETS,  # v2: facets measured on the mesh (set seeds)
                              2: _SCANLINES,  # v3: virtual scanlines
                              3: _SCAN_CIRCLES,  # v4: Mauldon's scan circles
                              4: _KINDS}  # v5: trace kinds (fracture, vein, fault, bedding)


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def to_blob(array: np.ndarray) -> bytes:
    """The `.npy` bytes of an array (format version 1.0). The header of a plain dtype is written here (np.save's
    bytes, but for the spare room np.save may leave for appending): 4× faster, for the thousands of small
    arrays an extraction stores on the GUI thread."""
    array = np.ascontiguousarray(array)
    descr = array.dtype.str
    if array.dtype.fields is not None or array.dtype.hasobject or not _NPY_DESCR.fullmatch(descr):
        buf = io.BytesIO()
        np.save(buf, array, allow_pickle=False)
        return buf.getvalue()
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {array.shape!r}, }}"
    header += " " * (-(len(header) + 11) % 64) + "\n"  # the data starts 64-byte aligned, as np.save's
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode("latin1") + array.tobytes()


def from_blob(blob: bytes | None) -> np.ndarray | None:
    """The array of a `.npy` blob (a writable copy). The blobs `to_blob` writes (version 1.0, C order, plain
    dtype) are decoded here from their header; anything else goes through `np.load`. np.load parses every
    header with `ast.literal_eval`: 60 µs a blob, a 0.1–0.8 s freeze of the window opening a project of
    a thousand small arrays."""
    if blob is None:
        return None
    header = _NPY_HEADER.match(blob)
    if header is None:
        return np.load(io.BytesIO(blob), allow_pickle=False)
    dtype = np.dtype(header["descr"].decode())
    shape = tuple(int(n) for n in header["shape"].split(b",") if n.strip())
    count = math.prod(shape)
    offset = 10 + int.from_bytes(header["length"], "little")
    if len(blob) != offset + count * dtype.itemsize:
        raise ProjectError(f"a stored array is damaged: {len(blob)} bytes, expected {offset + count * dtype.itemsize} "
                           f"for shape {shape} of {dtype}")
    return np.frombuffer(blob, dtype, count, offset).reshape(shape).copy()


# `np.save`'s version 1.0 header of a C-ordered array of a plain (non-structured, non-object) dtype
_NPY_DESCR = re.compile(r"[<>|=][a-zA-Z]\d*")
_NPY_HEADER = re.compile(rb"\x93NUMPY\x01\x00(?P<length>..)\{'descr': '(?P<descr>[<>|=][a-zA-Z]\d*)', "
                         rb"'fortran_order': False, 'shape': \((?P<shape>[\d, ]*)\), \} *\n", re.DOTALL)


def _stored(read):
    """A reading method whose rows do not decode (a JSON text, an array blob, a camera, an absent table)
    reports the project file as damaged, naming what it read, instead of failing inside the decoder."""
    @functools.wraps(read)
    def checked(self, *args, **kwargs):
        try:
            return read(self, *args, **kwargs)
        except (ValueError, TypeError, KeyError, EOFError, sqlite3.DatabaseError, InputError) as exc:
            what = read.__name__ + (f" {args[0]!r}" if args and isinstance(args[0], str) else "")
            raise ProjectError(f"{self.path}: the project file is damaged: its {what} cannot be read "
                               f"({type(exc).__name__}: {exc}); restore it from a backup") from exc
    return checked


class Project:
    """An open project. Use `Project.create` or `Project.open`, ideally as a context manager."""

    def __init__(self, path: Path, connection: sqlite3.Connection, lock: io.TextIOWrapper | None):
        self.path = path
        self._db = connection
        self._lock = lock
        self._verified: set[tuple[Path, int, float]] = set()  # inputs re-hashed and found unchanged, by stat
        self.origin = _origin(path, self._meta("origin"))

    # -- opening and closing ------------------------------------------------------------------------

    @classmethod
    def create(cls, path: str | Path, *, mesh_path: str | Path, cameras: dict[str, Camera],
               images: dict[str, Path] | None = None, origin: np.ndarray | None = None,
               camera_file: str | Path | None = None) -> Project:
        """Make a new project file referencing the mesh and photos; refuses to overwrite.

        cameras : in the WORLD frame, read from `camera_file` (named in errors). images : photo path per
        camera name (optional). origin : the local origin (world metres); by default the mesh's bounding-box
        centre. Refused when no camera sees the mesh (`check_cameras_see`). The file appears only when
        complete (written beside it, then renamed).
        """
        path = Path(path)
        if path.exists():
            raise ProjectError(f"{path}: a file of that name exists; choose another name or delete it")
        if not path.parent.is_dir():
            raise ProjectError(f"{path}: the folder {path.parent} does not exist; create it first")
        mesh_path = Path(mesh_path).resolve()
        mesh = read_mesh(mesh_path, origin=origin)
        check_cameras_see(cameras, mesh.vertices + mesh.origin, camera_file)
        tmp = path.with_name(path.name + ".creating")
        tmp.unlink(missing_ok=True)
        db = sqlite3.connect(tmp)
        try:
            db.executescript(_SCHEMA_V1 + "".join(MIGRATIONS[v] for v in range(1, SCHEMA_VERSION)))
            db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
            base = path.resolve().parent
            with db:
                db.executemany("INSERT INTO meta VALUES (?, ?)", [
                    ("origin", json.dumps(mesh.origin.tolist())), ("created_by", "tracemap 0.1.0")])
                db.execute("INSERT INTO inputs VALUES ('mesh', ?, ?, ?, ?)", _reference(mesh_path, base))
                for name, camera in cameras.items():
                    photo = (images or {}).get(name)
                    ref = _reference(Path(photo).resolve(), base) if photo else (None, None, None, None)
                    db.execute("INSERT INTO images VALUES (?, ?, ?, ?, ?, ?)",
                               (name, json.dumps(camera.to_dict()), *ref))
            db.close()
            os.replace(tmp, path)
        except BaseException:
            db.close()
            tmp.unlink(missing_ok=True)
            raise
        return cls.open(path)

    @classmethod
    def open(cls, path: str | Path) -> Project:
        """Open an existing project, taking its lock. An older schema is read as it is and upgraded by the
        first edit, inside that edit's transaction, after a backup (`transaction`)."""
        path = Path(path)
        if not path.is_file():
            raise ProjectError(f"{path}: project file not found")
        _check_header(path)
        lock_path = path.with_name(path.name + ".lock")
        made_lock = not lock_path.exists()
        lock = _take_lock(path)
        try:
            db = sqlite3.connect(path, timeout=5.0)
            try:
                _check_schema(path, db)
            finally:
                db.close()
            return cls(path, _connect(path), lock)
        except BaseException:
            if made_lock:  # opening a file that is no project leaves nothing beside it
                lock_path.unlink(missing_ok=True)
            lock.close()
            raise

    def for_thread(self) -> Project:
        """Another handle on this open project, for one worker thread: its own SQLite connection (make it,
        use it and close it on that thread), under this project's lock. WAL lets the other connections
        read while it writes; writers wait for each other."""
        return Project(self.path, _connect(self.path), None)

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None
            if self._lock is not None:
                self._lock.close()

    def __enter__(self) -> Project:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """All writes inside are one atomic edit: committed together or not at all."""
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        backup = None
        try:
            backup = self._upgrade(db)
            yield db
            db.execute("COMMIT")
        except BaseException as exc:
            if db.in_transaction:  # SQLite rolls back by itself on some errors (a full disk); ROLLBACK would fail
                db.execute("ROLLBACK")
            if backup is not None:  # the file is as it was: no upgrade to keep a copy from
                backup.unlink(missing_ok=True)
            if isinstance(exc, sqlite3.OperationalError) and exc.sqlite_errorcode == sqlite3.SQLITE_FULL:
                raise ProjectError(f"{self.path}: the disk is full (SQLite: {exc}); nothing was written and the "
                                   "project is unchanged. Free some space and try again") from exc
            raise

    def _upgrade(self, db: sqlite3.Connection) -> Path | None:
        """Bring an older schema up to date inside the open transaction, so the upgrade commits with the edit
        or not at all and a failed command leaves an older project as it was. Under the write lock no other
        handle is upgrading, and the version read is the file's. Returns the backup made for it, if any."""
        version = db.execute("PRAGMA user_version").fetchone()[0]
        if version >= SCHEMA_VERSION:
            return None
        backup = self._backup(version)
        for v in range(version, SCHEMA_VERSION):
            for statement in filter(str.strip, MIGRATIONS[v].split(";")):
                db.execute(statement)
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        return backup

    def _backup(self, version: int) -> Path | None:
        """A copy of the file as it is (`<stem>.v<N>.bak<suffix>`), so an older tracemap can still open the
        original; None if one is there already (from an attempt that was cut off: the file is unchanged since).
        Written under a temporary name and renamed when complete, so a cut-off copy is never taken for it."""
        backup = self.path.with_name(f"{self.path.stem}.v{version}.bak{self.path.suffix}")
        if backup.exists():
            return None
        partial = backup.with_name(backup.name + ".writing")
        source, copy = sqlite3.connect(self.path, timeout=5.0), sqlite3.connect(partial)
        try:  # a second connection reads the file as committed: the write lock held here does not block it
            source.backup(copy)
            copy.close()
            os.replace(partial, backup)
        except BaseException:
            copy.close()
            partial.unlink(missing_ok=True)
            raise
        finally:
            source.close()
        return backup

    @property
    def schema_version(self) -> int:
        """The schema the file is in: older than `SCHEMA_VERSION` until its first edit upgrades it."""
        return self._db.execute("PRAGMA user_version").fetchone()[0]

    # -- inputs -------------------------------------------------------------------------------------

    @property
    def base_dir(self) -> Path:
        return self.path.resolve().parent

    @_stored
    def cameras(self, *, local: bool = True) -> dict[str, Camera]:
        """Cameras by image name, in the local frame (default) or the world frame."""
        rows = self._db.execute("SELECT name, camera FROM images ORDER BY name").fetchall()
        cams = {name: Camera.from_dict(json.loads(blob)) for name, blob in rows}
        return {n: c.shifted(self.origin) for n, c in cams.items()} if local else cams

    @_stored
    def image_path(self, name: str) -> Path | None:
        """The photo of image `name`, checked unchanged since it was added; None if it has no photo."""
        row = self._db.execute("SELECT path, size, mtime, sha256 FROM images WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise ProjectError(f"{self.path}: no image named {name!r}")
        if row[0] is None:
            return None
        return self._checked(f"photo of image {name!r}", *row)

    @property
    @_stored
    def mesh_path(self) -> Path:
        row = self._db.execute("SELECT path, size, mtime, sha256 FROM inputs WHERE role = 'mesh'").fetchone()
        return self._checked("mesh", *row)

    def load_mesh(self) -> Mesh:
        """The mesh in the project's local frame (checked unchanged)."""
        return read_mesh(self.mesh_path, origin=self.origin)

    def _checked(self, what: str, rel: str, size: int, mtime: float, sha: str) -> Path:
        path = (self.base_dir / rel).resolve()
        if not path.is_file():
            raise ProjectError(f"{self.path}: the {what} was moved or deleted: {path} not found")
        stat = path.stat()
        if stat.st_size == size and stat.st_mtime == mtime or (path, stat.st_size, stat.st_mtime) in self._verified:
            return path
        if stat.st_size != size or file_digest(path) != sha:
            raise ProjectError(f"{self.path}: the {what} changed since it was added to the project: {path} "
                               "(size or SHA-256 differ); restore the original file")
        self._verified.add((path, stat.st_size, stat.st_mtime))  # a copied file: hashed once, not at every use
        return path

    # -- traces -------------------------------------------------------------------------------------

    @_stored
    def traces2d(self, images: Iterable[str] | None = None) -> list[Trace2D]:
        sql = f"SELECT id, image, polyline, source, component, {self._kind_column} FROM traces2d"
        if images is None:
            rows = self._db.execute(sql + " ORDER BY id").fetchall()
        else:  # only these photos' blobs are read and decoded (the index on image finds them)
            wanted = sorted(set(images))
            rows = self._db.execute(f"{sql} WHERE image IN ({', '.join('?' * len(wanted))}) ORDER BY id",
                                    wanted).fetchall()
        return [Trace2D(i, im, from_blob(p), s, c, k) for i, im, p, s, c, k in rows]

    @property
    def _kind_column(self) -> str:
        """What to read a trace's kind from: every trace of a file from before kinds (schema 4) is a fracture."""
        return "kind" if self.schema_version >= 5 else "'fracture'"

    def traces2d_counts(self) -> dict[str, int]:
        """How many 2D traces each photo has (photos with none are left out), without reading the traces."""
        return dict(self._db.execute("SELECT image, count(*) FROM traces2d GROUP BY image").fetchall())

    def add_traces2d(self, traces: Iterable[Trace2D], db: sqlite3.Connection | None = None, *,
                     relabel: bool = True) -> list[int]:
        """Insert traces (their ids are ignored) and return the new ids; inside `db`'s transaction if given.

        relabel : label the 2D connected components of their photos afresh (`relabel_traces2d`). The editor
        passes False: its undo restores traces with the labels they had, and it labels a photo's traces itself.
        """
        traces = list(traces)
        with _maybe(self, db) as db:
            ids = [db.execute("INSERT INTO traces2d (image, polyline, source, component, kind) VALUES (?, ?, ?, ?, ?)",
                              (t.image, to_blob(t.polyline), t.source, t.component, t.kind)).lastrowid
                   for t in traces]
            if relabel:
                self.relabel_traces2d({t.image for t in traces}, db)
            return ids

    def update_traces2d(self, traces: Iterable[Trace2D], db: sqlite3.Connection | None = None) -> None:
        """Store edited traces (matched by id): polyline, source, component and kind."""
        with _maybe(self, db) as db:
            db.executemany("UPDATE traces2d SET image = ?, polyline = ?, source = ?, component = ?, kind = ? "
                           "WHERE id = ?",
                           [(t.image, to_blob(t.polyline), t.source, t.component, t.kind, t.id) for t in traces])

    def remove_traces2d(self, ids: Iterable[int], db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.executemany("DELETE FROM traces2d WHERE id = ?", [(int(i),) for i in ids])

    def restore_traces2d(self, traces: Iterable[Trace2D], db: sqlite3.Connection | None = None) -> None:
        """Re-insert removed traces under their own ids (undo of a removal)."""
        with _maybe(self, db) as db:
            db.executemany("INSERT INTO traces2d (id, image, polyline, source, component, kind) "
                           "VALUES (?, ?, ?, ?, ?, ?)",
                           [(t.id, t.image, to_blob(t.polyline), t.source, t.component, t.kind) for t in traces])

    def delete_traces2d(self, image: str, source: str, db: sqlite3.Connection) -> list[int]:
        """Delete the 2D traces of `image` made by `source` (manual | auto), relabel the components of those
        left (`relabel_traces2d`); returns the ids deleted."""
        where = "FROM traces2d WHERE image = ? AND source = ?"
        ids = [r[0] for r in db.execute(f"SELECT id {where}", (image, source))]
        db.execute(f"DELETE {where}", (image, source))
        self.relabel_traces2d([image], db)
        return ids

    def relabel_traces2d(self, images: Iterable[str], db: sqlite3.Connection | None = None) -> None:
        """Store the 2D connected component of every trace on these photos, labelled afresh over all of them
        (`engine.delineate.components.label_components`: traces that cross or touch share a label)."""
        # imported here: the delineation package takes a second to import, and opening a project needs none of it
        from engine.delineate.components import label_components

        with _maybe(self, db) as db:
            for image in sorted(set(images)):
                traces = self.traces2d([image])
                camera = json.loads(db.execute("SELECT camera FROM images WHERE name = ?", (image,)).fetchone()[0])
                labelled, _ = label_components(traces, (camera["height"], camera["width"]))
                changed = [(t.component, t.id) for t, old in zip(labelled, traces) if t.component != old.component]
                db.executemany("UPDATE traces2d SET component = ? WHERE id = ?", changed)

    @_stored
    def traces3d(self) -> list[Trace3D]:
        columns = _T3_COLUMNS.replace("kind", self._kind_column)
        rows = self._db.execute(f"SELECT id, {columns} FROM traces3d ORDER BY id").fetchall()
        return [_row_to_trace3d(r) for r in rows]

    def add_traces3d(self, traces: Iterable[Trace3D], db: sqlite3.Connection | None = None) -> list[int]:
        with _maybe(self, db) as db:
            return [db.execute(f"INSERT INTO traces3d ({_T3_COLUMNS}) VALUES ({_T3_MARKS})",
                               _trace3d_to_row(t)).lastrowid for t in traces]

    def update_traces3d(self, traces: Iterable[Trace3D], db: sqlite3.Connection | None = None) -> None:
        """Store edited traces (matched by id): every field."""
        sets = ", ".join(f"{f} = ?" for f in _T3_FIELDS)
        with _maybe(self, db) as db:
            db.executemany(f"UPDATE traces3d SET {sets} WHERE id = ?",
                           [(*_trace3d_to_row(t), t.id) for t in traces])

    def remove_traces3d(self, ids: Iterable[int], db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.executemany("DELETE FROM traces3d WHERE id = ?", [(int(i),) for i in ids])

    def restore_traces3d(self, traces: Iterable[Trace3D], db: sqlite3.Connection | None = None) -> None:
        """Re-insert removed traces under their own ids (undo of a removal)."""
        with _maybe(self, db) as db:
            db.executemany(f"INSERT INTO traces3d (id, {_T3_COLUMNS}) VALUES (?, {_T3_MARKS})",
                           [(t.id, *_trace3d_to_row(t)) for t in traces])

    def map_names(self) -> list[str]:
        return [r[0] for r in self._db.execute("SELECT name FROM maps ORDER BY name")]

    @_stored
    def vertex_map(self, name: str) -> tuple[np.ndarray, dict]:
        """A per-vertex scalar map of the mesh (e.g. "p21" or "p32:set1") and how it was made."""
        values, info = self._map_row(name, "vertex_values, info")
        return from_blob(values), json.loads(info)

    @_stored
    def map_info(self, name: str) -> dict:
        """How a stored map was made (`vertex_map`'s second item), without reading its values."""
        return json.loads(self._map_row(name, "info")[0])

    def _map_row(self, name: str, columns: str) -> tuple:
        row = self._db.execute(f"SELECT {columns} FROM maps WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise ProjectError(f"{self.path}: no map named {name!r}; available: {', '.join(self.map_names()) or 'none'}"
                               " (run `tracemap analyse` first)")
        return row

    def set_vertex_maps(self, maps: dict[str, np.ndarray], info: dict, db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.executemany("INSERT OR REPLACE INTO maps VALUES (?, ?, ?)",
                           [(name, to_blob(values), json.dumps(info)) for name, values in maps.items()])

    @_stored
    def result(self, name: str, default: object = None) -> object:
        """A stored analysis result (JSON), e.g. "sets" or "topology"."""
        row = self._db.execute("SELECT value FROM results WHERE name = ?", (name,)).fetchone()
        return default if row is None else json.loads(row[0])

    def set_result(self, name: str, value: object, db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.execute("INSERT OR REPLACE INTO results VALUES (?, ?)", (name, json.dumps(value, default=jsonable)))

    def remove_result(self, name: str, db: sqlite3.Connection | None = None) -> None:
        """Forget a stored result (undo of the run that first stored it)."""
        with _maybe(self, db) as db:
            db.execute("DELETE FROM results WHERE name = ?", (name,))

    def record_basis(self, names: Iterable[str], traces: list[Trace3D], db: sqlite3.Connection | None = None) -> None:
        """Note that the results `names` (keys of RESULT_BASIS) were computed on `traces`, as stored."""
        with _maybe(self, db) as db:
            row = db.execute("SELECT value FROM results WHERE name = 'basis'").fetchone()
            basis = {} if row is None else json.loads(row[0])
            basis.update({n: traces_digest(traces, RESULT_BASIS[n]) for n in names})
            self.set_result("basis", basis, db)

    @_stored
    def stale_results(self, traces: list[Trace3D] | None = None) -> list[str]:
        """The stored results computed on other traces than the project's 3D traces now (or `traces`): after a
        merge, a trim, a new extraction or an edit of what they depend on. Results from before the basis was
        recorded are not judged."""
        basis = self.result("basis") or {}
        traces = self.traces3d() if traces is None else traces
        return [n for n in RESULT_BASIS if n in basis and self.result(n) is not None
                and basis[n] != traces_digest(traces, RESULT_BASIS[n])]

    @_stored
    def gcps(self) -> dict[str, dict]:
        """Ground-control points: name → {"world": [x, y, z], "observations": {image: [u, v]}}."""
        rows = self._db.execute("SELECT name, world, observations FROM gcps ORDER BY name").fetchall()
        return {n: {"world": json.loads(w), "observations": json.loads(o)} for n, w, o in rows}

    def set_gcp(self, name: str, world: list[float], observations: dict[str, list[float]],
                db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.execute("INSERT OR REPLACE INTO gcps VALUES (?, ?, ?)",
                       (name, json.dumps([float(x) for x in world]), json.dumps(observations)))

    def remove_gcp(self, name: str, db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.execute("DELETE FROM gcps WHERE name = ?", (name,))

    @_stored
    def registration(self) -> Registration | None:
        """The model → world registration of `tracemap register` (MATHS §11), or None before one was made."""
        stored = self.result("registration")
        return None if stored is None else Registration.from_dict(stored)

    def set_registration(self, registration: Registration | None, db: sqlite3.Connection | None = None) -> None:
        """Store a registration (None removes it: exports go back to the model frame)."""
        with _maybe(self, db) as db:
            if registration is None:
                db.execute("DELETE FROM results WHERE name = 'registration'")
            else:
                self.set_result("registration", registration.to_dict(), db)

    @_stored
    def facets(self) -> list[Facet]:
        """Fracture-plane facets measured on the mesh (local frame), by id: seeds of the set fitting."""
        if self.schema_version < 2:  # not upgraded yet: no facets table
            return []
        rows = self._db.execute(f"SELECT id, {_FACET_COLUMNS} FROM facets ORDER BY id").fetchall()
        return [_row_to_facet(r) for r in rows]

    def add_facet(self, facet: Facet, db: sqlite3.Connection | None = None) -> int:
        """Store a facet (its id is ignored) and return its new id."""
        with _maybe(self, db) as db:
            return db.execute(f"INSERT INTO facets ({_FACET_COLUMNS}) VALUES ({_FACET_MARKS})",
                              _facet_to_row(facet)).lastrowid

    def remove_facet(self, facet_id: int, db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.execute("DELETE FROM facets WHERE id = ?", (int(facet_id),))

    def restore_facet(self, facet: Facet, db: sqlite3.Connection | None = None) -> None:
        """Re-insert a removed facet under its own id (undo of a removal)."""
        with _maybe(self, db) as db:
            db.execute(f"INSERT INTO facets (id, {_FACET_COLUMNS}) VALUES (?, {_FACET_MARKS})",
                       (facet.id, *_facet_to_row(facet)))

    @_stored
    def scanlines(self) -> list[Scanline]:
        """The virtual scanlines laid on the mesh (local frame), by id."""
        if self.schema_version < 3:  # not upgraded yet: no scanlines table
            return []
        rows = self._db.execute("SELECT id, name, start_point, end_point, reach FROM scanlines ORDER BY id")
        return [Scanline(from_blob(a), from_blob(b), reach, name, id_) for id_, name, a, b, reach in rows]

    def add_scanline(self, line: Scanline, db: sqlite3.Connection | None = None) -> int:
        """Store a scanline (its id is ignored) and return its new id."""
        with _maybe(self, db) as db:
            return db.execute("INSERT INTO scanlines (name, start_point, end_point, reach) VALUES (?, ?, ?, ?)",
                              _scanline_row(line)).lastrowid

    def remove_scanline(self, scanline_id: int, db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.execute("DELETE FROM scanlines WHERE id = ?", (int(scanline_id),))

    def restore_scanline(self, line: Scanline, db: sqlite3.Connection | None = None) -> None:
        """Re-insert a removed scanline under its own id (undo of a removal)."""
        with _maybe(self, db) as db:
            db.execute("INSERT INTO scanlines (id, name, start_point, end_point, reach) VALUES (?, ?, ?, ?, ?)",
                       (line.id, *_scanline_row(line)))

    @_stored
    def scan_circles(self) -> list[ScanCircle]:
        """The scan circles laid on the mesh (local frame), by id."""
        if self.schema_version < 4:  # not upgraded yet: no scan_circles table
            return []
        rows = self._db.execute("SELECT id, name, centre, radius FROM scan_circles ORDER BY id")
        return [ScanCircle(from_blob(centre), radius, name, id_) for id_, name, centre, radius in rows]

    def add_scan_circle(self, circle: ScanCircle, db: sqlite3.Connection | None = None) -> int:
        """Store a scan circle (its id is ignored) and return its new id."""
        with _maybe(self, db) as db:
            return db.execute("INSERT INTO scan_circles (name, centre, radius) VALUES (?, ?, ?)",
                              (circle.name, to_blob(circle.centre), circle.radius)).lastrowid

    def remove_scan_circle(self, circle_id: int, db: sqlite3.Connection | None = None) -> None:
        with _maybe(self, db) as db:
            db.execute("DELETE FROM scan_circles WHERE id = ?", (int(circle_id),))

    def restore_scan_circle(self, circle: ScanCircle, db: sqlite3.Connection | None = None) -> None:
        """Re-insert a removed scan circle under its own id (undo of a removal)."""
        with _maybe(self, db) as db:
            db.execute("INSERT INTO scan_circles (id, name, centre, radius) VALUES (?, ?, ?, ?)",
                       (circle.id, circle.name, to_blob(circle.centre), circle.radius))

    @_stored
    def setting(self, key: str, default: object = None) -> object:
        """A stored user setting (view state, tool parameters), JSON-decoded."""
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (f"setting:{key}",)).fetchone()
        return default if row is None else json.loads(row[0])

    def set_setting(self, key: str, value: object, db: sqlite3.Connection | None = None) -> None:
        """Store a user setting (JSON-encodable); inside `db`'s transaction if given."""
        with _maybe(self, db) as db:
            db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (f"setting:{key}", json.dumps(value)))

    def delete_traces3d_of(self, parents: Iterable[int], db: sqlite3.Connection) -> int:
        """Delete the 3D traces made from any of these 2D traces; returns how many."""
        parents = set(parents)
        doomed = [r[0] for r in db.execute("SELECT id, parents FROM traces3d")
                  if parents.intersection(json.loads(r[1]))]
        db.executemany("DELETE FROM traces3d WHERE id = ?", [(i,) for i in doomed])
        return len(doomed)

    def _meta(self, key: str) -> str:
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        if row is None:
            raise ProjectError(f"{self.path}: the project has no {key!r} entry; the file is damaged")
        return row[0]


_T3_FIELDS = ("points", "uv", "face", "image_index", "images", "parents", "component", "normal", "method",
              "K", "M", "dispersion", "set_id", "term_start", "term_end", "extra", "kind")
_T3_COLUMNS = ", ".join(_T3_FIELDS)
_T3_MARKS = ", ".join("?" * len(_T3_FIELDS))


def _trace3d_to_row(t: Trace3D) -> tuple:
    return (to_blob(t.points), to_blob(t.uv), to_blob(t.face), to_blob(t.image_index), json.dumps(t.images),
            json.dumps(t.parents), t.component, None if t.normal is None else to_blob(t.normal), t.method,
            _real(t.K), _real(t.M), _real(t.dispersion), t.set_id, t.term_start, t.term_end,
            json.dumps(t.extra), t.kind)


def _row_to_trace3d(row: tuple) -> Trace3D:
    (id_, points, uv, face, image_index, images, parents, component, normal, method, K, M, dispersion,
     set_id, term_start, term_end, extra, kind) = row
    return Trace3D(id_, from_blob(points), from_blob(uv), from_blob(face), from_blob(image_index),
                   tuple(json.loads(images)), tuple(json.loads(parents)), component, from_blob(normal), method,
                   _nan(K), _nan(M), _nan(dispersion), set_id, term_start, term_end, json.loads(extra), kind)


_FACET_COLUMNS = "centroid, normal, planarity, rms, n_points, radius, faces, rejected_reason"
_FACET_MARKS = ", ".join("?" * 8)


def _facet_to_row(f: Facet) -> tuple:
    return (to_blob(np.asarray(f.centroid, dtype=float)), to_blob(np.asarray(f.normal, dtype=float)),
            float(f.planarity), float(f.rms), int(f.n_points), float(f.radius),
            to_blob(np.asarray(f.faces, dtype=np.int64)), f.rejected_reason)


def _row_to_facet(row: tuple) -> Facet:
    id_, centroid, normal, planarity, rms, n_points, radius, faces, reason = row
    return Facet(from_blob(normal), from_blob(centroid), planarity, rms, n_points, reason, radius, from_blob(faces),
                 id_)


def _scanline_row(line: Scanline) -> tuple:
    return line.name, to_blob(line.start), to_blob(line.end), float(line.reach)


def _real(x: float) -> float | None:
    """SQLite keeps ±inf (M = inf for an exactly planar trace) but not NaN, which becomes NULL."""
    return None if x is None or np.isnan(x) else float(x)


def _nan(x: float | None) -> float:
    return np.nan if x is None else float(x)


@contextmanager
def _maybe(project: Project, db: sqlite3.Connection | None) -> Iterator[sqlite3.Connection]:
    if db is not None:
        yield db
    else:
        with project.transaction() as own:
            yield own


def _reference(path: Path, base: Path) -> tuple[str, int, float, str]:
    if not path.is_file():
        raise ProjectError(f"{path}: file not found")
    try:
        rel = os.path.relpath(path, base)
    except ValueError:  # another drive on Windows
        rel = str(path)
    stat = path.stat()
    return rel, stat.st_size, stat.st_mtime, file_digest(path)


def _connect(path: Path) -> sqlite3.Connection:
    db = sqlite3.connect(path, timeout=5.0)
    db.isolation_level = None  # explicit transactions only: one per edit
    db.execute("PRAGMA journal_mode = WAL")
    db.execute("PRAGMA foreign_keys = ON")
    return db


def _take_lock(path: Path) -> io.TextIOWrapper:
    lock = open(path.with_name(path.name + ".lock"), "a+")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().strip() or "another process"
        lock.close()
        raise ProjectError(f"{path}: the project is open in {holder}; close it there first") from None
    lock.seek(0)
    lock.truncate()
    lock.write(f"process {os.getpid()}")
    lock.flush()
    return lock


def _check_header(path: Path) -> None:
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise ProjectError(f"{path}: cannot read the project file: {exc.strerror}") from None
    if head != b"SQLite format 3\x00":
        raise ProjectError(f"{path}: not a tracemap project (not an SQLite database)")


def _check_schema(path: Path, db: sqlite3.Connection) -> int:
    """The file's schema version, after checking it holds every table and column that version has."""
    try:
        version = db.execute("PRAGMA user_version").fetchone()[0]
        found = _columns(db)
    except sqlite3.DatabaseError as exc:
        raise ProjectError(f"{path}: not a tracemap project ({exc})") from exc
    if "meta" not in found:
        raise ProjectError(f"{path}: not a tracemap project (no meta table)")
    if version > SCHEMA_VERSION:
        raise ProjectError(f"{path}: made by a newer tracemap (schema {version}; this program reads up to "
                           f"{SCHEMA_VERSION}); upgrade tracemap to open it")
    if version < 1:
        raise ProjectError(f"{path}: the project file is damaged: schema version {version}, expected 1 to "
                           f"{SCHEMA_VERSION}; restore it from a backup")
    for table, columns in _expected_columns(version).items():
        missing = sorted(columns - found.get(table, set()))
        if missing:
            what = f"table {table!r}" if table not in found else f"column(s) {', '.join(missing)} of table {table!r}"
            raise ProjectError(f"{path}: the project file is damaged: {what} missing; restore it from a backup")
    return version


def _columns(db: sqlite3.Connection) -> dict[str, set[str]]:
    tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
    return {t: {r[1] for r in db.execute(f"PRAGMA table_info({t!r})")} for t in tables}


def _expected_columns(version: int) -> dict[str, set[str]]:
    """The tables and columns of a schema version, from the statements that make it."""
    db = sqlite3.connect(":memory:")
    try:
        db.executescript(_SCHEMA_V1 + "".join(MIGRATIONS[v] for v in range(1, version)))
        return {t: c for t, c in _columns(db).items() if not t.startswith("sqlite_")}
    finally:
        db.close()


def _origin(path: Path, stored: str) -> np.ndarray:
    try:
        origin = np.array(json.loads(stored), dtype=np.float64)
    except (ValueError, TypeError):
        origin = None
    if origin is None or origin.shape != (3,) or not np.isfinite(origin).all():
        raise ProjectError(f"{path}: the project file is damaged: its origin is {stored[:40]!r}, expected three "
                           "numbers; restore it from a backup")
    return origin


SIZELESS_FORMATS = ("bundler", "nvm", "openmvs")
"""Camera files that do not give the photos' size: it comes from the photos, or is given."""


def new_project(path: str | Path, mesh_path: str | Path, camera_file: str | Path, *,
                images: str | Path | None = None, image_list: str | Path | None = None,
                image_size: tuple[int, int] | None = None) -> Project:
    """`tracemap new` and the application's New project: read the cameras (any format `engine.cameras`
    reads), check the photos in `images` if given (each found, of its camera's size), and create the
    project (`Project.create`: refused over an existing file, or when no camera sees the mesh). Returns it
    open; nothing is written when any of it fails.

    image_list : Bundler's list of images. image_size : (width, height) of every photo, for camera files
    that do not store it (`SIZELESS_FORMATS`) when the photos are not at hand.
    """
    if image_size is not None and detect_format(camera_file) not in SIZELESS_FORMATS:
        raise InputError(camera_file, "an image size is for Bundler, NVM and OpenMVS files, which do not store "
                                      "the photos' size; this file gives the size of every camera")
    cameras = read_cameras(camera_file, image_dir=images, image_list=image_list, image_sizes=image_size)
    linked = check_images(cameras, images) if images else None
    return Project.create(path, mesh_path=mesh_path, cameras=cameras, images=linked, camera_file=camera_file)

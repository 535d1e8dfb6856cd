"""Content-addressed artifact store on fsspec (``file://``, ``memory://``, ``s3://``...).

A store URL is all a user gives: ``./.volcap/store``, ``file:///mnt/cap/store``,
``memory://ci``, ``s3://bucket/volcap``. Credentials and endpoints of object storage come from
the environment (``AWS_ACCESS_KEY_ID``, ``AWS_ENDPOINT_URL``...), never from the URL or a file.

Layout under the root::

    objects/<hex[:2]>/<hex[2:]>   immutable bytes; the name is the BLAKE3 of the content
    refs/<name>                   named roots (``captures/demo``...): canonical JSON ArtifactRef
    tmp/<uuid>                    writes in flight; moved into objects/ only when complete
    prefect/results/<key>         Prefect's cache records (task results: references only)

Guarantees (tested in ``tests/test_store.py`` on every backend):

- A put is atomic: bytes go to ``tmp/`` first and are renamed (or, on object storage, written
  with one PUT / completed multipart upload) under their digest only when complete. A crash,
  even ``kill -9``, leaves at most a stray ``tmp/`` file that ``gc`` removes later.
- Two writers of the same digest write the same bytes: whoever renames last wins, harmlessly.
- Reads verify the digest (default for records; ``verify()`` checks everything): a corrupt or
  missing object raises :class:`CorruptObjectError` / :class:`MissingObjectError` naming the
  digest, never returns wrong bytes.
- ``gc`` deletes only objects no ref reaches and only when older than a grace period, so an object
  a concurrent writer is putting (or has just re-used) survives. A put that finds its object
  already present refreshes its timestamp for the same reason.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

import fsspec
from fsspec.implementations.local import LocalFileSystem

from volcap_core.digest import CHUNK_BYTES, StreamingDigest, digest_bytes, digest_file
from volcap_core.files import open_atomic, write_atomic
from volcap_core.records import (
    DIGEST_RE,
    MEDIA_BYTES,
    MEDIA_TREE,
    ArtifactRef,
    Record,
    canonical_json,
)

DEFAULT_STORE_URL = "./.volcap/store"
TREE_FORMAT = "volcap-tree/1"
_TREE_HEAD = b'{"entries":{'  # canonical manifests start so (sorted keys)
REF_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*(/[A-Za-z0-9][A-Za-z0-9._-]*)*$")
#: Objects and temporary files younger than this are never collected: a writer may be using them.
DEFAULT_GRACE_S = 3600.0

R = TypeVar("R", bound=Record)


class StoreError(Exception):
    """Base of store errors; the message names the digest, ref or path concerned."""


class MissingObjectError(StoreError, KeyError):
    def __init__(self, digest: str, store: str):
        self.digest = digest
        super().__init__(f"object {digest} is not in store {store}")

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


class CorruptObjectError(StoreError):
    def __init__(self, digest: str, actual: str, store: str):
        self.digest, self.actual = digest, actual
        super().__init__(f"object {digest} in store {store} is corrupt: its content hashes to {actual}")


class InvalidTreeError(StoreError, ValueError):
    pass


class MissingRefError(StoreError, KeyError):
    def __str__(self) -> str:
        return self.args[0]


def _as_digest(ref_or_digest: ArtifactRef | str) -> str:
    digest = ref_or_digest.digest if isinstance(ref_or_digest, ArtifactRef) else ref_or_digest
    if not DIGEST_RE.match(digest):
        raise ValueError(f"not a blake3 digest: {digest!r}")
    return digest


def normalize_store_url(url: str) -> str:
    """Plain paths become absolute ``file://`` URLs so every process names the store alike."""
    if "://" not in url:
        return "file://" + str(Path(url).expanduser().resolve())
    return url.rstrip("/")


# ---------------------------------------------------------------------------------------------
# Trees
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TreeEntry:
    digest: str
    size: int


def validate_tree_path(path: str) -> str:
    """A tree path is relative POSIX, with no empty, ``.`` or ``..`` segment and no backslash."""
    if not path or path.startswith("/") or "\\" in path or "\x00" in path:
        raise InvalidTreeError(f"tree path {path!r} is not a relative POSIX path")
    if re.match(r"^[A-Za-z]:", path):
        raise InvalidTreeError(f"tree path {path!r} is absolute (drive letter)")
    for seg in path.split("/"):
        if seg in ("", ".", ".."):
            raise InvalidTreeError(f"tree path {path!r} has a {seg or 'empty'!r} segment")
    return path


def encode_tree(entries: dict[str, TreeEntry]) -> bytes:
    """Canonical manifest bytes of a tree (paths validated)."""
    body = {}
    for path in entries:
        validate_tree_path(path)
        e = entries[path]
        if not DIGEST_RE.match(e.digest):
            raise InvalidTreeError(f"tree entry {path!r}: bad digest {e.digest!r}")
        body[path] = {"digest": e.digest, "size": int(e.size)}
    _refuse_file_directory_clash(body)
    return canonical_json({"format": TREE_FORMAT, "entries": body})


def _refuse_file_directory_clash(paths: Iterable[str], name: str = "tree") -> None:
    """``a`` and ``a/b`` cannot both be files: such a tree cannot be written to a folder."""
    files = set(paths)
    for path in sorted(files):
        parts = path.split("/")
        for i in range(1, len(parts)):
            folder = "/".join(parts[:i])
            if folder in files:
                raise InvalidTreeError(f"{name}: {folder!r} is both a file and a folder (of {path!r})")


def decode_tree(data: bytes, name: str = "tree") -> dict[str, TreeEntry]:
    """Parse and validate a manifest: canonical encoding, no duplicate/absolute/``..`` paths."""

    def no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [k for k, _ in pairs]
        if len(keys) != len(set(keys)):
            dup = sorted({k for k in keys if keys.count(k) > 1})
            raise InvalidTreeError(f"{name}: duplicate path(s) {dup}")
        return dict(pairs)

    try:
        doc = json.loads(data.decode("utf-8"), object_pairs_hook=no_duplicates)
    except InvalidTreeError:
        raise
    except (ValueError, UnicodeDecodeError) as exc:
        raise InvalidTreeError(f"{name}: not a JSON manifest ({exc})") from exc
    if not isinstance(doc, dict) or set(doc) != {"format", "entries"} or doc["format"] != TREE_FORMAT \
            or not isinstance(doc["entries"], dict):
        raise InvalidTreeError(f"{name}: not a {TREE_FORMAT} manifest")
    entries: dict[str, TreeEntry] = {}
    for path, e in doc["entries"].items():
        try:
            validate_tree_path(path)
        except InvalidTreeError as exc:
            raise InvalidTreeError(f"{name}: {exc}") from None
        # type() rather than isinstance(): JSON true/false are Python bools, and bools are ints.
        if not isinstance(e, dict) or set(e) != {"digest", "size"} or type(e["size"]) is not int \
                or not isinstance(e["digest"], str) or not DIGEST_RE.match(e["digest"]) or e["size"] < 0:
            raise InvalidTreeError(f"{name}: bad entry for {path!r}: {e!r}")
        entries[path] = TreeEntry(e["digest"], e["size"])
    if canonical_json(doc) != data:
        raise InvalidTreeError(f"{name}: manifest is not canonically encoded")
    _refuse_file_directory_clash(entries, name)
    return entries


# ---------------------------------------------------------------------------------------------
# The store
# ---------------------------------------------------------------------------------------------


@dataclass
class GcReport:
    kept: int = 0
    deleted: int = 0
    deleted_bytes: int = 0
    young_unreachable: int = 0  # unreachable but within the grace period
    tmp_deleted: int = 0
    deleted_digests: list[str] = field(default_factory=list)


@dataclass
class VerifyReport:
    checked: int = 0
    bytes: int = 0
    corrupt: list[str] = field(default_factory=list)
    dangling: list[str] = field(default_factory=list)  # "ref-or-digest -> missing digest"

    @property
    def ok(self) -> bool:
        return not self.corrupt and not self.dangling


class ArtifactStore:
    """A content-addressed store at ``url``. Cheap to construct; safe to share across threads."""

    def __init__(self, url: str = DEFAULT_STORE_URL):
        self.url = normalize_store_url(url)
        options: dict[str, Any] = {}
        if "::" not in self.url and fsspec.utils.get_protocol(self.url) not in ("file", "local", "memory"):
            # Other processes write and delete here too: a cached listing (s3fs keeps one per
            # directory it lists, e.g. after gc/verify) would hide their objects and refs.
            options["use_listings_cache"] = False
        self.fs, root = fsspec.core.url_to_fs(self.url, **options)
        self.root = root.rstrip("/")
        self._local = isinstance(self.fs, LocalFileSystem)
        if self._local:
            for sub in ("objects", "refs", "tmp"):
                os.makedirs(self._p(sub), exist_ok=True)

    def __repr__(self) -> str:
        return f"ArtifactStore({self.url!r})"

    # -- paths -------------------------------------------------------------------------------
    def _p(self, *parts: str) -> str:
        return "/".join([self.root, *parts])

    def _object_path(self, digest: str) -> str:
        hexd = digest.split(":", 1)[1]
        return self._p("objects", hexd[:2], hexd[2:])

    def _ref_path(self, name: str) -> str:
        if not REF_NAME_RE.match(name):
            raise ValueError(f"invalid ref name {name!r} (letters, digits, '._-' and '/' separators)")
        return self._p("refs", name)

    # -- low-level atomic write ------------------------------------------------------------
    def _tmp_path(self) -> str:
        return self._p("tmp", f"{uuid.uuid4().hex}.part")

    def _commit(self, tmp: str, final: str) -> None:
        """Move a complete temporary file to its final name (atomic rename on a local disk)."""
        if self._local:
            os.makedirs(os.path.dirname(final), exist_ok=True)
            os.replace(tmp, final)
        else:
            self.fs.mv(tmp, final)

    def _write_atomic(self, final: str, data: bytes) -> None:
        """Write small bytes under ``final`` atomically: temporary file, then rename/one PUT."""
        if not self._local:
            # One PUT is atomic on object storage and in memory: the object appears whole or not.
            self.fs.pipe_file(final, bytes(data))
            return
        os.makedirs(os.path.dirname(final), exist_ok=True)
        # The temporary file goes to tmp/, not beside ``final``: objects/ and refs/ must only ever
        # hold complete entries, and gc collects what a killed writer leaves in tmp/.
        write_atomic(final, data, tmp_dir=self._p("tmp"))

    def _discard(self, path: str) -> None:
        try:
            self.fs.rm_file(path)
        except (FileNotFoundError, OSError):
            pass

    def _fresh(self, path: str, grace_s: float) -> bool | None:
        """None when ``path`` is absent; else whether it was modified within half the grace period."""
        try:
            info = self.fs.info(path)
        except FileNotFoundError:
            return None
        age = time.time() - _mtime(info)
        return age < grace_s / 2

    def _touch_existing(self, digest: str, grace_s: float = DEFAULT_GRACE_S) -> bool:
        """True when the object exists; refreshes its timestamp so a concurrent gc keeps it."""
        path = self._object_path(digest)
        if self._local:
            try:
                os.utime(path)
                return True
            except FileNotFoundError:
                return False
        fresh = self._fresh(path, grace_s)
        if fresh is None:
            return False
        return fresh  # stale objects on object storage are rewritten (a PUT is the only "touch")

    # -- blobs -------------------------------------------------------------------------------
    def put_bytes(self, data: bytes, media_type: str = MEDIA_BYTES) -> ArtifactRef:
        digest = digest_bytes(data)
        if not self._touch_existing(digest):
            self._write_atomic(self._object_path(digest), bytes(data))
        return ArtifactRef(digest=digest, size=len(data), media_type=media_type)

    def put_stream(self, stream: BinaryIO, media_type: str = MEDIA_BYTES) -> ArtifactRef:
        """Store everything left in ``stream``, hashing while copying, in ``CHUNK_BYTES`` chunks."""
        tmp = self._tmp_path()
        hasher = StreamingDigest()
        try:
            if not self._local:
                self.fs.makedirs(self._p("tmp"), exist_ok=True)
            with (open(tmp, "wb") if self._local else self.fs.open(tmp, "wb")) as out:
                while chunk := stream.read(CHUNK_BYTES):
                    hasher.update(chunk)
                    out.write(chunk)
                if self._local:
                    out.flush()
                    os.fsync(out.fileno())
            digest = hasher.digest
            if self._touch_existing(digest):
                self._discard(tmp)
            else:
                self._commit(tmp, self._object_path(digest))
        except BaseException:
            self._discard(tmp)
            raise
        return ArtifactRef(digest=digest, size=hasher.size, media_type=media_type)

    def put_file(self, path: str | Path, media_type: str = MEDIA_BYTES, *, check_first: bool = False) -> ArtifactRef:
        """Store a local file. ``check_first``: hash it before copying, and copy nothing when the
        object is already stored: one read instead of a copy, an fsync and a delete when the file is
        likely stored already (a rerun storing the same folder: 27 ms -> 1 ms a file measured on a
        busy disk), one extra read when it is not. A file changing in between is stored as read."""
        if check_first:
            digest, size = digest_file(path)
            if self._touch_existing(digest):
                return ArtifactRef(digest=digest, size=size, media_type=media_type)
        with open(path, "rb") as f:
            return self.put_stream(f, media_type)

    def exists(self, ref_or_digest: ArtifactRef | str) -> bool:
        return self.fs.exists(self._object_path(_as_digest(ref_or_digest)))

    def missing(self, refs: Iterable[ArtifactRef | str]) -> list[str]:
        """Digests among ``refs`` that are not in the store.

        On an asynchronous filesystem (S3 and the like) the existence checks go out concurrently,
        64 at a time, instead of one round trip after another (a cache check of a camera's 24 frames
        was 24 sequential requests)."""
        digests = list({_as_digest(r) for r in refs})
        if len(digests) > 1 and getattr(self.fs, "async_impl", False):
            from fsspec.asyn import sync

            async def check() -> list[bool]:
                import asyncio

                found: list[bool] = []
                for i in range(0, len(digests), 64):
                    found += await asyncio.gather(*(self.fs._exists(self._object_path(d))
                                                    for d in digests[i:i + 64]))
                return found

            return [d for d, ok in zip(digests, sync(self.fs.loop, check)) if not ok]
        return [d for d in digests if not self.exists(d)]

    def get_bytes(self, ref_or_digest: ArtifactRef | str, verify: bool = True) -> bytes:
        digest = _as_digest(ref_or_digest)
        try:
            data = self.fs.cat_file(self._object_path(digest))
        except FileNotFoundError:
            raise MissingObjectError(digest, self.url) from None
        if verify:
            actual = digest_bytes(data)
            if actual != digest:
                raise CorruptObjectError(digest, actual, self.url)
        return data

    def open(self, ref_or_digest: ArtifactRef | str) -> BinaryIO:
        """Unverified streaming read (use :meth:`get_file` to copy out with verification)."""
        digest = _as_digest(ref_or_digest)
        try:
            return self.fs.open(self._object_path(digest), "rb")
        except FileNotFoundError:
            raise MissingObjectError(digest, self.url) from None

    def get_file(self, ref_or_digest: ArtifactRef | str, dest: str | Path, verify: bool = True) -> Path:
        """Copy an object to a local file in chunks, verifying on the way; atomic at ``dest``."""
        digest = _as_digest(ref_or_digest)
        dest = Path(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        hasher = StreamingDigest()
        with self.open(digest) as src, open_atomic(dest) as out:
            while chunk := src.read(CHUNK_BYTES):
                hasher.update(chunk)
                out.write(chunk)
            if verify and hasher.digest != digest:   # raised inside: dest keeps what it held
                raise CorruptObjectError(digest, hasher.digest, self.url)
        return dest

    def size(self, ref_or_digest: ArtifactRef | str) -> int:
        digest = _as_digest(ref_or_digest)
        try:
            return int(self.fs.info(self._object_path(digest))["size"])
        except FileNotFoundError:
            raise MissingObjectError(digest, self.url) from None

    def iter_objects(self) -> Iterator[tuple[str, dict]]:
        """Every stored object as ``(digest, fsspec info)``."""
        base = self._p("objects")
        try:
            listing = self.fs.find(base, detail=True)
        except FileNotFoundError:
            return
        for path, info in sorted(listing.items()):
            rel = path[len(base):].strip("/").split("/") if path.startswith(base) else \
                path.split("/objects/", 1)[-1].split("/")
            if len(rel) != 2 or len(rel[0]) != 2:
                continue
            digest = "blake3:" + rel[0] + rel[1]
            if DIGEST_RE.match(digest):
                yield digest, info

    # -- records -----------------------------------------------------------------------------
    def put_record(self, record: Record) -> ArtifactRef:
        return self.put_bytes(record.to_canonical_json(), record.media_type())

    def get_record(self, ref: ArtifactRef | str, model: type[R], verify: bool = True) -> R:
        data = self.get_bytes(ref, verify=verify)
        try:
            return model.from_json_bytes(data)
        except ValueError as exc:
            raise StoreError(f"object {_as_digest(ref)} is not a valid {model.__name__}: {exc}") from exc

    def put_json(self, obj: Any, media_type: str = "application/json") -> ArtifactRef:
        return self.put_bytes(canonical_json(obj), media_type)

    def get_json(self, ref: ArtifactRef | str, verify: bool = True) -> Any:
        return json.loads(self.get_bytes(ref, verify=verify))

    # -- trees -------------------------------------------------------------------------------
    def put_tree(self, entries: dict[str, ArtifactRef | TreeEntry]) -> ArtifactRef:
        """Store a manifest of ``relative path → object`` (the objects must already be stored)."""
        norm = {p: TreeEntry(e.digest, e.size) for p, e in entries.items()}
        missing = self.missing(e.digest for e in norm.values())
        if missing:
            raise MissingObjectError(missing[0], self.url)
        return self.put_bytes(encode_tree(norm), MEDIA_TREE)

    def put_directory(self, directory: str | Path,
                      progress: Callable[[int, int], None] | None = None) -> ArtifactRef:
        """Store every file under a local directory, then its tree (symlinks are refused)."""
        directory = Path(directory)
        files = sorted(p for p in directory.rglob("*") if p.is_file() or p.is_symlink())
        entries: dict[str, ArtifactRef] = {}
        for i, p in enumerate(files):
            if p.is_symlink():
                raise InvalidTreeError(f"{p}: symbolic links are not stored (copy the file instead)")
            entries[p.relative_to(directory).as_posix()] = self.put_file(p, check_first=True)
            if progress:
                progress(i + 1, len(files))
        return self.put_tree(entries)

    def get_tree(self, ref: ArtifactRef | str, verify: bool = True) -> dict[str, TreeEntry]:
        digest = _as_digest(ref)
        return decode_tree(self.get_bytes(digest, verify=verify), name=f"tree {digest}")

    def get_directory(self, ref: ArtifactRef | str, dest: str | Path, verify: bool = True) -> Path:
        dest = Path(dest)
        for path, entry in self.get_tree(ref).items():
            self.get_file(entry.digest, dest / path, verify=verify)
        return dest

    # -- named refs --------------------------------------------------------------------------
    def set_ref(self, name: str, ref: ArtifactRef) -> None:
        if not self.exists(ref):
            raise MissingObjectError(ref.digest, self.url)
        data = canonical_json(ref.model_dump(mode="json"))
        self._write_atomic(self._ref_path(name), data)

    def get_ref(self, name: str) -> ArtifactRef:
        try:
            data = self.fs.cat_file(self._ref_path(name))
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            # A directory is a namespace of refs ("captures" of "captures/demo"), not a ref.
            raise MissingRefError(f"no ref named {name!r} in store {self.url}") from None
        return ArtifactRef.model_validate_json(data)

    def delete_ref(self, name: str) -> None:
        path = self._ref_path(name)
        missing = MissingRefError(f"no ref named {name!r} in store {self.url}")
        # Object storage deletes an absent key without complaint: ask first there.
        if not self._local and not self.fs.isfile(path):
            raise missing
        try:
            self.fs.rm_file(path)
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            raise missing from None

    def list_refs(self, prefix: str = "") -> dict[str, ArtifactRef]:
        base = self._p("refs")
        try:
            paths = self.fs.find(base)
        except FileNotFoundError:
            return {}
        out = {}
        for path in sorted(paths):
            name = path.split("/refs/", 1)[-1] if not path.startswith(base) else path[len(base):].strip("/")
            if name.startswith(prefix) and REF_NAME_RE.match(name):
                out[name] = self.get_ref(name)
        return out

    def resolve(self, ref_or_name: str) -> ArtifactRef:
        """A digest (``blake3:…``) or a ref name → ArtifactRef.

        A named ref carries its media type; a bare digest is recognised as a tree by its content.
        """
        if DIGEST_RE.match(ref_or_name):
            media = MEDIA_TREE if self._is_tree(ref_or_name) else MEDIA_BYTES
            return ArtifactRef(digest=ref_or_name, size=self.size(ref_or_name), media_type=media)
        return self.get_ref(ref_or_name)

    def _is_tree(self, digest: str) -> bool:
        try:
            head = self.fs.cat_file(self._object_path(digest), start=0, end=len(_TREE_HEAD))  # ranged
            if head != _TREE_HEAD:
                return False
            self.get_tree(digest)
            return True
        except (FileNotFoundError, StoreError):
            return False

    # -- reachability, gc, verify ------------------------------------------------------------
    def children(self, digest: str) -> set[str]:
        """Digests a JSON object (tree or record) mentions; other objects have none."""
        path = self._object_path(digest)
        try:
            # One ranged read: never the whole of a large blob (and on S3, not a 50 MB block).
            data = self.fs.cat_file(path, start=0, end=_JSON_SNIFF_BYTES)
            if not _looks_like_json_text(data):
                return set()
            if len(data) >= _JSON_SNIFF_BYTES:
                data = self.fs.cat_file(path)  # JSON text is parsed whole anyway
        except FileNotFoundError:
            return set()
        try:
            doc = json.loads(data.decode("utf-8"))
        except ValueError:  # UnicodeDecodeError is a ValueError
            return set()
        return set(_digests_in(doc))

    def reachable(self, roots: Iterable[str]) -> set[str]:
        seen: set[str] = set()
        stack = [d for d in roots]
        while stack:
            d = stack.pop()
            if d in seen:
                continue
            seen.add(d)
            stack.extend(c for c in self.children(d) if c not in seen)
        return seen

    def gc(self, grace_s: float = DEFAULT_GRACE_S, dry_run: bool = False,
           extra_roots: Iterable[str] = ()) -> GcReport:
        """Delete objects no ref reaches, except those younger than ``grace_s`` seconds."""
        roots = [r.digest for r in self.list_refs().values()] + list(extra_roots)
        live = self.reachable(roots)
        now = time.time()
        report = GcReport()
        for digest, info in list(self.iter_objects()):
            if digest in live:
                report.kept += 1
                continue
            if now - _mtime(info) < grace_s:
                report.young_unreachable += 1
                report.kept += 1
                continue
            if not dry_run:
                # The listing may be minutes old by now: a writer may have re-put (refreshed) this
                # object since. Look again right before deleting.
                path = self._object_path(digest)
                try:
                    current = self.fs.info(path)
                except FileNotFoundError:
                    continue
                if time.time() - _mtime(current) < grace_s:
                    report.young_unreachable += 1
                    report.kept += 1
                    continue
                self._discard(path)
            report.deleted += 1
            report.deleted_bytes += int(info.get("size", 0))
            report.deleted_digests.append(digest)
        try:
            tmp_files = self.fs.find(self._p("tmp"), detail=True)
        except FileNotFoundError:
            tmp_files = {}
        for path, info in tmp_files.items():
            if now - _mtime(info) >= grace_s:
                if not dry_run:
                    self._discard(path)
                report.tmp_deleted += 1
        return report

    def verify(self, progress: Callable[[int, int], None] | None = None) -> VerifyReport:
        """Re-hash every object and check every ref's closure is present."""
        report = VerifyReport()
        objects = list(self.iter_objects())
        present = {d for d, _ in objects}
        for i, (digest, _) in enumerate(objects):
            hasher = StreamingDigest()
            with self.fs.open(self._object_path(digest), "rb") as f:
                while chunk := f.read(CHUNK_BYTES):
                    hasher.update(chunk)
            report.checked += 1
            report.bytes += hasher.size
            if hasher.digest != digest:
                report.corrupt.append(digest)
            if progress:
                progress(i + 1, len(objects))
        for name, ref in self.list_refs().items():
            for d in sorted(self.reachable([ref.digest])):
                if d not in present:
                    report.dangling.append(f"{name} -> {d}")
        return report

    def du(self) -> dict[str, Any]:
        """Object count and bytes in all, and the bytes each ref keeps alive."""
        sizes = {d: int(info.get("size", 0)) for d, info in self.iter_objects()}
        per_ref = {}
        for name, ref in self.list_refs().items():
            closure = self.reachable([ref.digest])
            per_ref[name] = {"objects": len(closure & sizes.keys()),
                             "bytes": sum(sizes.get(d, 0) for d in closure)}
        return {"objects": len(sizes), "bytes": sum(sizes.values()), "refs": per_ref}


_JSON_SNIFF_BYTES = 64 << 10
#: A digest anywhere in a string: a whole value, a dict key, or inside a URI-like value. gc keeps
#: whatever a record mentions; keeping too much is harmless, deleting a referenced object is not.
_DIGEST_IN_TEXT = re.compile(r"(?<![0-9A-Za-z])blake3:[0-9a-f]{64}(?![0-9A-Za-z])")


def _looks_like_json_text(head: bytes) -> bool:
    """Whether the first bytes of an object can begin a JSON object or array (UTF-8 text).

    JSON text never holds a raw NUL and is valid UTF-8; binary formats (even one that happens to
    begin with ``{``, as a safetensors header length can) fail within the first bytes.
    """
    if head.lstrip(b" \t\r\n")[:1] not in (b"{", b"[") or b"\x00" in head:
        return False
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        return exc.start >= len(head) - 3 and len(head) >= _JSON_SNIFF_BYTES  # a cut character
    return True


def _digests_in(doc: Any) -> Iterator[str]:
    if isinstance(doc, str):
        yield from _DIGEST_IN_TEXT.findall(doc)
    elif isinstance(doc, dict):
        for k, v in doc.items():
            yield from _digests_in(k)
            yield from _digests_in(v)
    elif isinstance(doc, list):
        for v in doc:
            yield from _digests_in(v)


def _mtime(info: dict) -> float:
    """Modification time (epoch seconds) from an fsspec ``info`` of any backend."""
    for key in ("mtime", "LastModified", "last_modified", "created", "updated", "timeCreated"):
        v = info.get(key)
        if v is None:
            continue
        if isinstance(v, (int, float)):
            return float(v)
        if isinstance(v, _dt.datetime):
            if v.tzinfo is None:
                v = v.replace(tzinfo=_dt.timezone.utc)
            return v.timestamp()
        if isinstance(v, str):
            try:
                return _dt.datetime.fromisoformat(v.replace("Z", "+00:00")).timestamp()
            except ValueError:
                continue
    return 0.0  # unknown age counts as old: gc will still never touch reachable objects


def open_store(url: str | None = None) -> ArtifactStore:
    """The store at ``url``, else ``$VOLCAP_STORE``, else ``./.volcap/store``."""
    return ArtifactStore(url or os.environ.get("VOLCAP_STORE") or DEFAULT_STORE_URL)


__all__ = [
    "ArtifactStore", "open_store", "StoreError", "MissingObjectError", "CorruptObjectError",
    "InvalidTreeError", "MissingRefError", "TreeEntry", "encode_tree", "decode_tree",
    "GcReport", "VerifyReport", "DEFAULT_STORE_URL", "normalize_store_url",
]

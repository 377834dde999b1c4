"""Uploads: an import too big for one request body, sent in numbered parts and committed at once.

A client creates an upload (the body's format, its encoding and the import's mode), sends the
body's bytes in parts of any size up to ``VANTAGE_MAX_BODY_BYTES`` each (``PUT`` part ``n``;
sending a part again replaces it), and commits with the number of parts: the parts, in order,
are the import's body, decoded and stored all or nothing as a single import. A part may end
anywhere, even inside a line or a gzip stream, so a file can be cut by size alone.

Parts live as files under ``<data dir>/uploads/<doc>/<upload>/``, each written under a
temporary name, flushed to disk and renamed, so a part that is listed is whole; a killed server
keeps the parts it had and loses only the one arriving. Nothing reaches the document before the
commit, and the commit is the import route's: a kill during it leaves the previous version, and
the upload is put back at the next start-up, to commit again.
Uploads not touched for ``UPLOAD_KEEP_SECONDS`` are removed at start-up.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import re
import shutil
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import BinaryIO, Literal, cast

import xxhash

from .errors import Conflict, NotFound, TooMany, refused_when_full

__all__ = ["Claim", "MAX_PARTS", "Part", "Upload", "Uploads"]

log = logging.getLogger("vantage.import")
MAX_PARTS = 100_000  # parts an upload may have
UPLOAD_KEEP_SECONDS = 24 * 3600.0  # an upload untouched this long is removed at start-up
_PART = re.compile(r"^part-(\d{6})$")
_COMMITTING = ".committing"  # an upload set aside by a commit under way: ".<id>.committing"
_ID = re.compile(r"^[0-9a-f]{32}$")


@dataclass(frozen=True)
class Upload:
    """One upload: what its body is and how it is to be imported."""

    id: str
    doc: str
    format: Literal["ndjson", "json"]
    encoding: Literal["identity", "gzip"]
    mode: Literal["upsert", "replace"]


@dataclass(frozen=True)
class Part:
    number: int
    bytes: int
    xxh3: str  # xxh3-64 of the part's bytes, hex: a resuming client can tell what arrived


class Uploads:
    """The uploads under ``directory``, by document."""

    def __init__(self, directory: Path, max_bytes: int) -> None:
        self.directory, self.max_bytes = directory, max_bytes

    def new(self, doc: str, format: str, encoding: str, mode: str) -> Upload:
        upload = Upload(uuid.uuid4().hex, doc, format, encoding, mode)  # type: ignore[arg-type]
        where = self._path(doc, upload.id)
        where.mkdir(parents=True)
        _write_atomically(where / "upload.json", json.dumps(asdict(upload)).encode())
        return upload

    def get(self, doc: str, upload_id: str) -> Upload:
        """:raises NotFound: if there is no such upload of ``doc`` (never made, committed, removed)"""
        path = self._path(doc, upload_id) / "upload.json" if _ID.match(upload_id) else None
        try:
            if path is None:
                raise FileNotFoundError
            return Upload(**json.loads(path.read_bytes()))
        except FileNotFoundError:
            raise NotFound(
                f"no upload {upload_id!r} of document {doc!r}: never made, or committed or removed since"
            ) from None

    def parts(self, upload: Upload) -> list[Part]:
        """The parts received, in order."""
        out = []
        for path in sorted(self._path(upload.doc, upload.id).glob("part-*")):
            match = _PART.match(path.name)
            if match:
                digest = xxhash.xxh3_64()
                with open(path, "rb") as part:
                    for block in iter(lambda: part.read(1 << 20), b""):
                        digest.update(block)
                out.append(Part(int(match[1]), path.stat().st_size, digest.hexdigest()))
        return out

    def writer(self, upload: Upload, number: int) -> PartWriter:
        """Where part ``number`` is written; it counts only once ``PartWriter.keep`` ran.

        :raises Invalid: if ``number`` is not 1..MAX_PARTS (the route checks it first)
        """
        where = self._path(upload.doc, upload.id)
        others = [p for p in where.glob("part-*") if p.name != f"part-{number:06d}"]  # it replaces its own
        return PartWriter(where, number, self.max_bytes - sum(p.stat().st_size for p in others))

    def claim(self, upload: Upload, count: int) -> Claim:
        """Parts 1..``count`` of ``upload``, set aside for its commit (a second commit finds
        none): the caller imports ``Claim.body``, then ``finish`` es or ``give_back`` s it. The
        set-aside upload names its process, so one left by a process killed mid-commit is put
        back at the next start-up. Cost: a listing and a rename, no read.

        :raises Conflict: naming the parts missing, or received past ``count``
        :raises NotFound: if the upload is being committed already
        """
        where = self._path(upload.doc, upload.id)
        if not where.is_dir():
            raise NotFound(f"upload {upload.id!r} is being committed, or was")
        have = {int(m[1]) for p in where.glob("part-*") if (m := _PART.match(p.name))}
        missing = sorted(set(range(1, count + 1)) - have)
        extra = sorted(n for n in have if n > count)
        if missing or extra:
            why = [f"parts {_numbers(missing)} are missing"] if missing else []
            why += [f"parts {_numbers(extra)} were received past {count}"] if extra else []
            raise Conflict(
                f"upload {upload.id!r} cannot be committed as {count} parts: {'; '.join(why)}: "
                "nothing was imported"
            )
        aside = where.with_name(f".{upload.id}{_COMMITTING}")
        try:
            os.rename(where, aside)
        except FileNotFoundError:
            raise NotFound(f"upload {upload.id!r} is being committed, or was") from None
        (aside / "owner").write_text(str(os.getpid()))
        return Claim(where, aside, [aside / f"part-{n:06d}" for n in range(1, count + 1)])

    def remove(self, upload: Upload) -> None:
        shutil.rmtree(self._path(upload.doc, upload.id), ignore_errors=True)

    def remove_document(self, doc: str) -> None:
        """Every upload of ``doc`` (deleted)."""
        shutil.rmtree(self.directory / doc, ignore_errors=True)

    def sweep(self, keep: float = UPLOAD_KEEP_SECONDS) -> int:
        """Put back the uploads set aside by a commit whose process is gone (killed mid-commit:
        nothing was imported), and remove those nothing was sent to for ``keep`` seconds; how
        many were removed."""
        cutoff, removed = time.time() - keep, 0
        for where in self.directory.glob("*/*"):
            with contextlib.suppress(OSError, ValueError):  # gone already: another worker swept it
                if where.name.endswith(_COMMITTING):
                    if not _alive(int((where / "owner").read_text())):
                        (where / "owner").unlink()
                        os.rename(where, where.with_name(where.name[1 : -len(_COMMITTING)]))
                    continue
                touched = max((p.stat().st_mtime for p in where.iterdir()), default=where.stat().st_mtime)
                if touched < cutoff:
                    shutil.rmtree(where)
                    removed += 1
        if removed:
            log.info("removed %d uploads untouched for %g hours", removed, keep / 3600)
        return removed

    def _path(self, doc: str, upload_id: str) -> Path:
        return self.directory / doc / upload_id


class Claim:
    """An upload set aside for its commit (see ``Uploads.claim``)."""

    def __init__(self, home: Path, aside: Path, parts: list[Path]) -> None:
        self._home, self._aside = home, aside
        self.body = cast(BinaryIO, io.BufferedReader(_Concatenated(parts)))  # parts end to end

    def finish(self) -> None:
        """Imported: the parts go (blocking: a thread's work for big ones)."""
        self.body.close()
        shutil.rmtree(self._aside, ignore_errors=True)

    def give_back(self) -> None:
        """Not imported: the upload is back as it was, to mend and commit again."""
        self.body.close()
        with contextlib.suppress(FileNotFoundError):
            (self._aside / "owner").unlink()
            os.rename(self._aside, self._home)


class PartWriter:
    """One part as it arrives: written to a temporary file, then flushed and renamed by ``keep``."""

    def __init__(self, directory: Path, number: int, room: int) -> None:
        self.path = directory / f"part-{number:06d}"
        self._temporary = directory / f".part-{number:06d}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
        self._file = open(self._temporary, "wb")  # noqa: SIM115  (closed by keep or discard)
        self._digest, self.size, self._room = xxhash.xxh3_64(), 0, room

    @refused_when_full("keeping the upload's part")
    def write(self, chunk: bytes) -> None:
        """:raises TooMany: past the upload's room (VANTAGE_MAX_UPLOAD_BYTES, less what it holds)
        :raises StorageFull: if the disk is full (``discard`` it then)"""
        self.size += len(chunk)
        if self.size > self._room:
            raise TooMany(
                "the upload's parts would hold more than VANTAGE_MAX_UPLOAD_BYTES together: nothing "
                "of this part was kept"
            )
        self._digest.update(chunk)
        self._file.write(chunk)

    @refused_when_full("keeping the upload's part")
    def keep(self) -> Part:
        """Flush the part to disk and put it in place (replacing one sent before): blocking.

        :raises StorageFull: if the disk is full (``discard`` it then)"""
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        os.replace(self._temporary, self.path)
        return Part(int(self.path.name[5:]), self.size, self._digest.hexdigest())

    def discard(self) -> None:
        with contextlib.suppress(OSError):  # what it held, unwritten on a full disk: closed all the same
            self._file.close()
        self._temporary.unlink(missing_ok=True)


class _Concatenated(io.RawIOBase):
    """Files read one after another as one stream."""

    def __init__(self, paths: list[Path]) -> None:
        self._paths = list(reversed(paths))
        self._file: io.BufferedReader | None = None

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: memoryview) -> int:  # type: ignore[override]
        while True:
            if self._file is None:
                if not self._paths:
                    return 0
                self._file = open(self._paths.pop(), "rb")  # noqa: SIM115  (closed at its end)
            count = self._file.readinto(buffer)
            if count:
                return count
            self._file.close()
            self._file = None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        super().close()


def _write_atomically(path: Path, data: bytes) -> None:
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(temporary, "wb") as out:
        out.write(data)
        out.flush()
        os.fsync(out.fileno())
    os.replace(temporary, path)


def _numbers(numbers: list[int]) -> str:
    shown = ", ".join(map(str, numbers[:10]))
    return shown + (f" and {len(numbers) - 10} more" if len(numbers) > 10 else "")


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (on this host: uploads are a host's own)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's: alive
        return True
    return True

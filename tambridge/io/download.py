"""Download and unpack a TUM RGB-D sequence (needs internet; nothing else in tambridge does)."""

from __future__ import annotations

import re
import tarfile
import tempfile
import urllib.parse
import urllib.request
from pathlib import Path

from tqdm import tqdm

from tambridge.errors import TambridgeError

TUM_BASE_URL = "https://cvg.cit.tum.de/rgbd/dataset"
GZIP_START = b"\x1f\x8b"
_NAME = re.compile(r"^(?:fr|freiburg)([123])[/_]([a-z0-9_]+)$")


class DownloadError(TambridgeError):
    """A sequence name is not understood or the download or unpacking failed."""


def tum_archive_url(name: str, base_url: str = TUM_BASE_URL) -> tuple[str, str]:
    """``(url, folder name)`` of a TUM sequence such as ``fr1/desk`` or ``freiburg3_long_office_household``."""
    match = _NAME.match(name.strip().lower())
    if match is None:
        raise DownloadError(f"{name!r}: expected a TUM sequence name such as fr1/desk, fr2/xyz or fr3/long_office_household")
    if urllib.parse.urlparse(base_url).scheme not in ("http", "https", "file"):
        raise DownloadError(f"--base-url {base_url!r}: expected an http://, https:// or file:// address of a mirror of "
                            "the TUM dataset folder")
    camera, scene = match.groups()
    folder = f"rgbd_dataset_freiburg{camera}_{scene}"
    return f"{base_url.rstrip('/')}/freiburg{camera}/{folder}.tgz", folder


def download_tum(name: str, destination: Path, base_url: str = TUM_BASE_URL, progress: bool = True) -> Path:
    """Fetch and unpack a TUM sequence into ``destination``; returns the sequence folder.

    The archive is unpacked into a temporary folder and renamed into place, so an interrupted download never
    leaves a folder that looks like a sequence.
    """
    url, folder_name = tum_archive_url(name, base_url)
    destination = Path(destination)
    target = destination / folder_name
    if (target / "rgb.txt").is_file():
        return target
    if destination.exists() and not destination.is_dir():
        raise DownloadError(f"--to {destination}: is a file; give a folder")
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise DownloadError(f"{target}: exists and holds no sequence (no rgb.txt); move it away or give another --to")
    made = [folder for folder in (destination, *destination.parents) if not folder.exists()]
    destination.mkdir(parents=True, exist_ok=True)
    try:
        return _download_into(url, folder_name, destination, target, progress)
    except BaseException:
        # A failed download leaves no folder behind that it made.
        for folder in made:
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        raise


def _download_into(url: str, folder_name: str, destination: Path, target: Path, progress: bool) -> Path:
    with tempfile.TemporaryDirectory(prefix=f".{folder_name}.", dir=destination) as temp:
        archive = Path(temp) / "archive.tgz"
        try:
            with urllib.request.urlopen(url, timeout=60) as response, open(archive, "wb") as out:
                total = int(response.headers.get("Content-Length") or 0) or None
                with tqdm(total=total, unit="B", unit_scale=True, desc=folder_name, disable=not progress) as bar:
                    while chunk := response.read(1 << 20):
                        out.write(chunk)
                        bar.update(len(chunk))
        except OSError as error:
            raise DownloadError(f"{url}: download failed ({error}); check the network or pass --base-url") from error
        received = archive.stat().st_size
        if total is not None and received != total:
            raise DownloadError(f"{url}: got {received} of {total} bytes (the connection ended early); download it again")
        with open(archive, "rb") as head:
            if head.read(2) != GZIP_START:
                raise DownloadError(f"{url}: not a .tgz archive (an error page?); check --base-url")
        unpacked = Path(temp) / "unpacked"
        try:
            with tarfile.open(archive, "r:gz") as tar:
                tar.extractall(unpacked, filter="data")
        except tarfile.FilterError as error:
            raise DownloadError(f"{url}: the archive is unsafe ({error}); nothing was unpacked from it: check --base-url "
                                "and the mirror") from error
        except (tarfile.TarError, OSError, EOFError) as error:
            # gzip raises EOFError for an archive cut short.
            raise DownloadError(f"{url}: archive is corrupt or truncated ({error}); download it again") from error
        found = [p.parent for p in unpacked.rglob("rgb.txt")]
        if len(found) != 1:
            raise DownloadError(f"{url}: archive holds {len(found)} sequences (folders with rgb.txt), expected one")
        missing = [name for name in ("depth.txt", "rgb", "depth") if not (found[0] / name).exists()]
        if missing:
            raise DownloadError(f"{url}: the archive's sequence lacks {', '.join(missing)}; not a TUM sequence: check "
                                "--base-url and the mirror")
        if target.exists():
            target.rmdir()  # empty: checked before the download
        found[0].rename(target)
    return target

"""How a stage writes its outputs (every stage family uses it; it imports nothing of sellip): a file or a directory
built under a temporary name and renamed when complete (:func:`atomic_file`, :func:`atomic_directory`; every writer
of an output uses one of them, so a job killed mid-write leaves nothing at the output's path: docs/reliability.md),
progress lines for long loops (:func:`progress_logger`), an ordered thread map (:func:`map_in_threads`), and the
guard of commands that write into a user's folder (:func:`refuse_to_replace`, :func:`refuse_to_replace_folder`:
never replace what a user wrote unless told to, ``--force``).
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)




def _temporary_sibling(output: Path) -> Path:
    """A hidden sibling of ``output`` named for this process, with the same suffix (writers that go by it work)."""
    return output.with_name(f".{output.stem}.tmp-{os.getpid()}{output.suffix}")


@contextmanager
def atomic_file(output: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling path of the file ``output`` to write; on success it replaces ``output`` in one
    rename (a reader sees the old file or the new one, never a part), on error it is deleted. Creates the parent."""
    output = Path(output)
    tmp = _temporary_sibling(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    try:
        yield tmp
        os.replace(tmp, output)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(text: str, output: str | Path) -> Path:
    """Write ``text`` (UTF-8) to the file ``output`` atomically (:func:`atomic_file`). Returns ``output``."""
    with atomic_file(output) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(output)


@contextmanager
def atomic_directory(output: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of the directory ``output`` to write into (not yet created); rename it to
    ``output`` on success (replacing an old one), delete it on error. Creates the parent."""
    output = Path(output)
    tmp = output.parent / f".{output.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    output.parent.mkdir(parents=True, exist_ok=True)
    try:
        yield tmp
        if output.exists():
            shutil.rmtree(output)
        tmp.rename(output)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)



FORCE_HINT = "nothing was written; compare or move it aside, or run the same command with --force to replace it"


class WouldReplaceError(FileExistsError):
    """A command would replace a file or folder that a user may have written or edited; says which and what to do."""


def refuse_to_replace(path: str | Path, content: str | bytes, command: str, force: bool = False) -> None:
    """Raise WouldReplaceError when the file ``path`` exists with other content than ``content`` (str: UTF-8),
    unless ``force``. The same content, or no file, passes: running a command twice is harmless."""
    path = Path(path)
    if force or not path.exists():
        return
    data = content.encode("utf-8") if isinstance(content, str) else content
    if path.is_file() and path.read_bytes() == data:
        return
    raise WouldReplaceError(f"{path}: exists and differs from what {command} would write (edited since?); "
                            f"{FORCE_HINT}")


def refuse_to_replace_folder(path: str | Path, command: str, ours: Callable[[Path], bool],
                             force: bool = False) -> None:
    """Raise WouldReplaceError when the folder ``path`` exists, is not empty and ``ours(path)`` is false (it is not
    a folder that ``command`` wrote, which it replaces as a whole), unless ``force``."""
    path = Path(path)
    if force or not path.exists() or (path.is_dir() and (not any(path.iterdir()) or ours(path))):
        return
    raise WouldReplaceError(f"{path}: exists and is not a folder {command} wrote; {command} replaces the whole "
                            f"folder: give another --out, or {FORCE_HINT.split('; ', 1)[1]}")


def progress_logger(total: int, what: str, logger: logging.Logger = log,
                    every_s: float = 5.0) -> Callable[[int], None]:
    """A callback ``done(count)`` that logs progress with throughput at most every ``every_s`` seconds and at the
    end."""
    started = time.perf_counter()
    last = [started]

    def done(count: int) -> None:
        now = time.perf_counter()
        if count == total or now - last[0] >= every_s:
            last[0] = now
            logger.info("%s %d/%d (%.2f /s)", what, count, total, count / max(now - started, 1e-9))

    return done



def map_in_threads(function: Callable[[int], object], count: int, threads: int,
                   done: Callable[[int], None]) -> list:
    """``[function(i) for i in range(count)]`` on ``threads`` threads, calling ``done(n)`` as results arrive in order.

    On the first error the tasks not yet started are cancelled and the error is raised.
    """
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        futures = [pool.submit(function, i) for i in range(count)]
        results = []
        try:
            for future in futures:
                results.append(future.result())
                done(len(results))
        except BaseException:
            for future in futures:
                future.cancel()
            raise
    return results

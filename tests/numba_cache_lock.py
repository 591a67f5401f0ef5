"""Numba's on-disk cache, saved from several processes at once (the test suite's kernel warm-up beside its tests)."""

import fcntl

from numba.core.caching import IndexDataCacheFile


def serialise_numba_cache_saves() -> None:
    """Make every save into numba's cache in this process take an exclusive lock on a file beside the kernel's index.

    Numba names a new cached overload after the index it has just read: two processes saving different signatures of
    one kernel at once can take the same file name, and the index one writes then points at the code the other wrote.
    """
    save = IndexDataCacheFile.save

    def locked_save(self, key, data) -> None:
        # numba>=0.59 keeps the index's path here; should a later numba not, its saves go on unlocked as before.
        index_path = getattr(self, "_index_path", None)
        if index_path is None:
            return save(self, key, data)
        with open(index_path + ".lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            return save(self, key, data)

    IndexDataCacheFile.save = locked_save

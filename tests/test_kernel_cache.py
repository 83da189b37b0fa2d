"""nrhdr_core._drop_stale_kernel_caches: numba's cached kernels of the package go when any of its sources
changes (numba checks a kernel's own file only, not the modules it inlines from), and only then."""
import os

import nrhdr_core


def _tree(tmp_path):
    (tmp_path / "sub" / "__pycache__").mkdir(parents=True)
    (tmp_path / "__pycache__").mkdir()
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    caches = [tmp_path / "__pycache__" / "a.k-1.py311.nbi", tmp_path / "__pycache__" / "a.k-1.py311.1.nbc",
              tmp_path / "sub" / "__pycache__" / "b.k-3.py311.nbi"]
    for f in caches:
        f.write_bytes(b"cached")
    other = tmp_path / "__pycache__" / "a.cpython-311.pyc"
    other.write_bytes(b"bytecode")
    return caches, other


def test_caches_go_when_a_source_changes_and_only_then(tmp_path):
    caches, other = _tree(tmp_path)
    # no stored digest (a first run, or caches of an unknown version): dropped
    assert nrhdr_core._drop_stale_kernel_caches(tmp_path) is True
    assert not any(f.exists() for f in caches) and other.exists()
    # the same sources: new caches kept
    for f in caches:
        f.write_bytes(b"cached again")
    assert nrhdr_core._drop_stale_kernel_caches(tmp_path) is False
    assert all(f.exists() for f in caches)
    # one module changed (another module's kernels may inline it): every kernel cache of the package goes
    (tmp_path / "sub" / "b.py").write_text("y = 3\n")
    assert nrhdr_core._drop_stale_kernel_caches(tmp_path) is True
    assert not any(f.exists() for f in caches) and other.exists()
    assert nrhdr_core._drop_stale_kernel_caches(tmp_path) is False
    # a module added counts as a change
    (tmp_path / "c.py").write_text("")
    assert nrhdr_core._drop_stale_kernel_caches(tmp_path) is True


def test_unwritable_caches_left_as_they_are(tmp_path, monkeypatch):
    caches, _ = _tree(tmp_path)

    def refuse(self, missing_ok=False):
        raise PermissionError(f"{self}: read-only")
    with monkeypatch.context() as m:
        m.setattr(type(tmp_path), "unlink", refuse)
        assert nrhdr_core._drop_stale_kernel_caches(tmp_path) is False       # no error, nothing stamped
    assert all(f.exists() for f in caches)
    assert nrhdr_core._drop_stale_kernel_caches(tmp_path) is True            # writable again: dropped then


def test_the_package_itself_is_stamped():
    stamp = os.path.join(os.path.dirname(nrhdr_core.__file__), "__pycache__", "nrhdr-kernel-sources.sha256")
    assert os.path.isfile(stamp)
    assert nrhdr_core._drop_stale_kernel_caches() is False       # imported above: stamped, nothing to drop

"""numba's cache folder is keyed by every kernel source (``otbot_hw.model.kernel_cache``): a change to
a callee in another file can no longer leave a caller's stale compiled code in use."""
import re
import shutil
import subprocess
import sys
from pathlib import Path

from otbot_hw.model import kernel_cache

PKG = Path(kernel_cache.__file__).resolve().parent.parent
NJIT = re.compile(r"^@(numba\.)?(njit|jit|vectorize|guvectorize|register_jitable)\b", re.M)


def _compiled_modules() -> set[str]:
    return {p.relative_to(PKG).as_posix() for p in PKG.rglob("*.py") if NJIT.search(p.read_text())}


def test_every_file_with_compiled_kernels_is_in_the_hash():
    assert _compiled_modules() == set(kernel_cache.KERNEL_SOURCES)


def test_every_compiled_module_imports_the_model_package_before_its_first_kernel():
    """The cache folder is set by ``otbot_hw.model``'s import: it must come before any decoration."""
    for rel in kernel_cache.KERNEL_SOURCES:
        if rel.startswith("model/"):
            continue  # inside the package: its __init__ runs first
        text = (PKG / rel).read_text()
        first_kernel = NJIT.search(text).start()
        imp = re.search(r"^(from|import) otbot_hw\.model\b", text, re.M)
        assert imp is not None and imp.start() < first_kernel, rel


def test_the_folder_changes_with_any_kernel_source_and_only_with_them(tmp_path):
    root = tmp_path / "otbot_hw"
    shutil.copytree(PKG, root, ignore=shutil.ignore_patterns("__pycache__"))
    h0 = kernel_cache.sources_hash(root)
    (root / "recording" / "__init__.py").write_text("# not a kernel source\n")
    assert kernel_cache.sources_hash(root) == h0
    with open(root / "model" / "slip_law.py", "a") as f:  # a callee's file, not the caller's
        f.write("\n# changed\n")
    assert kernel_cache.sources_hash(root) != h0


def test_the_folder_follows_the_environment():
    h = kernel_cache.sources_hash()
    assert kernel_cache.cache_folder({"NUMBA_CACHE_DIR": "/x"}) == f"/x/otbot-{h}"
    assert kernel_cache.cache_folder({"XDG_CACHE_HOME": "/c"}) == f"/c/otbot/numba/{h}"


def test_the_kernels_are_cached_in_that_folder(tmp_path):
    code = ("import numba.core.config as c; from otbot_hw.simulation import integrators as i;"
            "from otbot_hw.model import kernel_cache as k;"
            "print(c.CACHE_DIR == k.cache_folder()); print(i.ext_rk4_into._cache._cache_path)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "XDG_CACHE_HOME": str(tmp_path)})
    same, path = out.stdout.split()
    assert same == "True" and path.startswith(str(tmp_path / "otbot" / "numba"))

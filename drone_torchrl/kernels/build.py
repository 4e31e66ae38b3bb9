"""Compile ``drone_kernels.cpp`` once per machine and load it.

The kernels are plain C++ with a C interface (no PyTorch headers: a build takes a few seconds
instead of the minute a ``torch.utils.cpp_extension`` build takes), compiled with the machine's C++
compiler (``$CXX``, else ``c++``/``g++``/``clang++``: the compiler ``torch.compile`` needs on CPU
anyway) for the machine's own instruction set (``-march=native``) and loaded with ``ctypes``.

There is one build per precision (float32, and float64 when a run asks for it), each a few
seconds of compilation. The shared library is cached in ``$DRONE_TORCHRL_CACHE`` (default ``~/.cache/drone_torchrl``,
under ``$XDG_CACHE_HOME`` when set), named by a hash of the source, the compiler, the flags and the
CPU's model and features: a later run on the same machine loads it in milliseconds, and a home
folder shared by cluster nodes of different CPUs keeps one build per kind of CPU (a ``-march=native``
build can crash on another CPU). It is written to a temporary file and renamed into place, so
concurrent first runs never load a half-written file.

Where no compiler works, :func:`library` returns None and :func:`unavailable_reason` says why;
``backend=fast`` is then refused in one line (:func:`~drone_torchrl.kernels.coverage.fast_refusal`).

:func:`scalar_check` compiles the source once more, syntax only (under a second), with
``-DDK_SCALAR_CHECK``: the single-source functions with one drone per thread (``V = float``,
``double``) and no vector type in sight.

Two more builds of the same source:

- :func:`cuda_library`: the CUDA engine (``nvcc -x cu``; one thread per drone), for tensors on a
  GPU. ``nvcc`` is ``$NVCC``, else on ``PATH``, else ``/usr/local/cuda/bin/nvcc``; a machine without
  it can load a library built elsewhere from ``$DRONE_TORCHRL_CUDA_LIBRARY`` (what
  ``benchmarks/gpu_check.sh`` carries to a GPU machine). :func:`build_cuda` compiles one into a
  given file; CI does, although it has no GPU.
- :func:`library` with ``scalar=True``: the scalar engine, the CPU engine with one drone per block,
  so the code every CUDA thread runs, run on the CPU (the tests compare it with the vector engine).
"""

from __future__ import annotations

import ctypes
import hashlib
import importlib.util
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from collections.abc import Callable
from functools import partial
from pathlib import Path

from drone_torchrl.envs.params import PARAM_NAMES

SOURCE = Path(__file__).with_name("drone_kernels.cpp")
CACHE_ENV = "DRONE_TORCHRL_CACHE"
# -ffp-contract=fast lets the compiler fuse a*b+c (as PyTorch's own CPU kernels do); no -ffast-math:
# NaN and inf must propagate so that a diverging run is detected.
BASE_FLAGS = ("-O3", "-std=c++17", "-fPIC", "-shared", "-fno-math-errno", "-ffp-contract=fast", "-pthread")
ARCH_FLAGS = ("-march=native",)
BUILD_TIMEOUT_S = 300
SCALAR_CHECK_FLAGS = ("-std=c++17", "-fsyntax-only", "-Wall", "-Werror", "-DDK_SCALAR_CHECK")
SCALAR_ENGINE_FLAGS = ("-DDK_SCALAR_ENGINE",)
CUDA_LIBRARY_ENV = "DRONE_TORCHRL_CUDA_LIBRARY"
# Ampere and Hopper machine code, and Hopper's PTX for newer GPUs (the driver compiles it on load).
CUDA_ARCHS = ("-gencode=arch=compute_80,code=sm_80", "-gencode=arch=compute_90,code=[sm_90,compute_90]")
# -cudart static: the library needs only the driver at run time, not a CUDA toolkit;
# --extended-lambda: the engines hand their work to the kernel as __host__ __device__ lambdas.
CUDA_FLAGS = ("-x", "cu", "-O3", "-std=c++17", "-shared", "-Xcompiler", "-fPIC", "-cudart", "static",
              "--extended-lambda", "-diag-suppress", "128,177", *CUDA_ARCHS)  # fmt: skip

#: The drone's constants in the kernels' order, which :func:`~.ops.env_constants` packs and a
#: library's ``DK_ENV_CONSTANTS`` must name when it loads: the fields of
#: :class:`~drone_torchrl.envs.params.DroneParams`, the values the kernels read derived from them
#: (its properties), then what is not the drone's.
ENV_CONSTANTS = (
    *PARAM_NAMES,
    *("weight", "arm_over_inertia", "floor", "zone_z_centre"),
    *("reward_zone", "reward_alive", "reward_terminated", "reset_noise"),
    "squash_high",  # the TanhNormal head's upper bound; < 0: the Normal head
    "reset_air",  # 1: start states drawn around the zone's centre, 0: on the floor
)

_lock = threading.Lock()
_state: dict[str, object] = {}


def cache_dir() -> Path:
    """The folder that keeps the compiled kernels: ``$DRONE_TORCHRL_CACHE``, else the user's cache folder."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "drone_torchrl"


def _which(*candidates: str | None) -> str | None:
    """The path of the first of ``candidates`` (names or paths, None skipped) that is found."""
    return next((found for c in candidates if c and (found := shutil.which(c))), None)


def _compiler() -> str | None:
    return _which(os.environ.get("CXX"), "c++", "g++", "clang++")


def _cpu_signature() -> str:
    """The CPU's model and feature flags (Linux), else what ``platform`` knows."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        keep = [line for line in lines if line.split(":")[0].strip() in ("model name", "flags", "Features")]
        return "\n".join(sorted(set(keep)))
    except OSError:
        return f"{platform.machine()} {platform.processor()}"


def _version(compiler: str) -> str:
    out = subprocess.run([compiler, "--version"], capture_output=True, text=True, timeout=60)
    return out.stdout.splitlines()[0] if out.stdout else compiler


def _compile(cmd: list[str], target: Path) -> str | None:
    """Run ``cmd -o <temporary file>`` and rename the file into ``target``: None, or why it failed."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so.tmp", dir=target.parent)
    os.close(fd)
    try:
        out = subprocess.run([*cmd, "-o", tmp], capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
        if out.returncode != 0:
            return f"{cmd[0]} failed: {_complaint(out)}"
        os.replace(tmp, target)
        return None
    except (OSError, subprocess.SubprocessError) as err:
        return f"{cmd[0]} failed: {err}"
    finally:
        Path(tmp).unlink(missing_ok=True)


def _complaint(out: subprocess.CompletedProcess) -> str:
    """A failed compiler's first error line (else its first line, else its exit status)."""
    errors = [line for line in out.stderr.splitlines() if "error" in line]
    return (errors or out.stderr.strip().splitlines() or [f"exit {out.returncode}"])[0]


def _build(compiler: str, target: Path, precision: tuple[str, ...]) -> str | None:
    """Compile into ``target``; returns None, or why it failed."""
    for arch in (ARCH_FLAGS, ()):  # some compilers (Apple clang on arm64) refuse -march=native
        why = _compile([compiler, *BASE_FLAGS, *precision, *arch, str(SOURCE)], target)
        if why is None:
            break
    return why


class _Unavailable(OSError):
    """Why a library cannot be had, in a message that is the reason as it stands."""


def _once(name: str, load: Callable[[], ctypes.CDLL]) -> ctypes.CDLL | None:
    """``load()``'s library, loaded once per process; None where it failed (:func:`unavailable_reason`)."""
    with _lock:
        if name not in _state:
            lib, reason = None, None
            try:
                lib = load()
            except (OSError, subprocess.SubprocessError) as err:
                reason = str(err) if isinstance(err, _Unavailable) else f"{type(err).__name__}: {err}"
            _state[name], _state["reason"] = lib, reason
        return _state[name]  # type: ignore[return-value]


def _from_cache(
    name: str, double: bool, compiler: str | None, missing: Exception, build: Callable, *key: str
) -> ctypes.CDLL:
    """Library ``name``, built by ``build(path)`` unless cached.

    Its cache file is named by a hash of the source, the compiler's version and ``key`` (flags,
    CPU...). Raises ``missing`` without a compiler, and a failed build's reason as its type.
    """
    if compiler is None:
        raise missing
    inputs = "\n".join((SOURCE.read_text(), _version(compiler), *key))
    path = cache_dir() / f"drone_kernels-{name}-{hashlib.sha256(inputs.encode()).hexdigest()[:16]}.so"
    if not path.is_file() and (why := build(path)) is not None:
        raise type(missing)(why)
    return _load(path, double)


def library(double: bool = False, scalar: bool = False) -> ctypes.CDLL | None:
    """The loaded kernels for float32 (or float64) tensors, built on first use; None if they cannot be.

    ``double``: float64. ``scalar``: the scalar engine (one drone per block).
    """
    name = ("scalar-" if scalar else "") + ("float64" if double else "float32")
    precision = (f"-DDK_DOUBLE={int(double)}",) + (SCALAR_ENGINE_FLAGS if scalar else ())
    flags = " ".join(BASE_FLAGS + precision + ARCH_FLAGS)
    missing = _Unavailable("no C++ compiler found (set CXX, or install g++ or clang++)")

    def load() -> ctypes.CDLL:
        compiler = _compiler()
        build = partial(_build, compiler, precision=precision)
        return _from_cache(name, double, compiler, missing, build, flags, _cpu_signature())

    return _once(name, load)


#: The entry points' argument lists the Python side calls (drone_kernels.cpp's ``dk_abi_version``).
ABI_VERSION = 4


class _Library(ctypes.CDLL):
    """A kernels library: its functions return an int64 (a size or a code), or a name."""

    _func_restype_ = ctypes.c_int64


def _load(path: Path, double: bool) -> ctypes.CDLL:
    lib = _Library(str(path))
    version = getattr(lib, "dk_abi_version", lambda: 1)()  # 1: built before the entry points were numbered
    if version != ABI_VERSION:
        raise OSError(
            f"{path} takes the entry points' arguments of version {version}, not {ABI_VERSION}: rebuild it"
        )
    for function in ("dk_env_constants", "dk_disturbance_constants", "dk_cuda_error"):
        if hasattr(lib, function):  # the last: the CUDA engine's only
            getattr(lib, function).restype = ctypes.c_char_p
    if lib.dk_real_bytes() != (8 if double else 4):
        raise OSError(f"{path} was built for another precision")
    _check_layout(lib, path)
    return lib


def _check_layout(lib: ctypes.CDLL, path: Path) -> None:
    """Raise OSError unless the kernels read the constants and see the observation Python packs.

    The kernels' constants are offsets into the arrays :mod:`.ops` packs: each name at its offset
    (``DK_ENV_CONSTANTS`` against :data:`ENV_CONSTANTS`, which DroneParams' fields begin, and the
    disturbance's against ``disturbances.FIELDS``), and the observation's width for every command
    memory (``disturbances.observation_names``).
    """
    from drone_torchrl.envs import disturbances  # torch: only once a library loads

    for function, packed in (
        ("dk_env_constants", ENV_CONSTANTS),
        ("dk_disturbance_constants", disturbances.FIELDS),
    ):
        read = tuple(getattr(lib, function)().decode().split(",")[:-1])
        if read != packed:
            raise OSError(
                f"{path.name} reads the constants {read} where drone_torchrl packs {packed} (drone_kernels.cpp's list)"
            )
    for k in range(disturbances.MAX_STEPS_BACK + 1):
        width = len(disturbances.observation_names({"observed_actions": k}))
        if lib.dk_observation_dim(k) != width:
            raise OSError(
                f"{path.name} sees {lib.dk_observation_dim(k)} observation entries with {k} observed commands; drone_torchrl {width}"
            )


def nvcc() -> str | None:
    """The CUDA compiler's path, or None.

    ``$NVCC``, else ``nvcc`` on ``PATH``, else the CUDA toolkit's, else the one the ``cuda`` extra
    installs (PyPI's ``nvidia-cuda-nvcc``).
    """
    spec = importlib.util.find_spec("nvidia")
    folders = (spec.submodule_search_locations or []) if spec else []
    pip = [str(Path(folder, "cu13", "bin", "nvcc")) for folder in folders]  # the cuda extra's
    return _which(os.environ.get("NVCC"), "nvcc", "/usr/local/cuda/bin/nvcc", *pip)


def build_cuda(target: Path, double: bool = False) -> str | None:
    """Compile the CUDA engine into ``target`` (no GPU needed): None, or why it failed."""
    compiler = nvcc()
    if compiler is None:
        return "no nvcc found (set NVCC, install the CUDA toolkit, or pip install 'drone_torchrl[cuda]')"
    return _compile([compiler, *CUDA_FLAGS, f"-DDK_DOUBLE={int(double)}", str(SOURCE)], target)


def cuda_library(double: bool = False) -> ctypes.CDLL | None:
    """The CUDA engine for float32 (``double``: float64) tensors, or None.

    ``$DRONE_TORCHRL_CUDA_LIBRARY`` (float32) when set, else built with :func:`nvcc` on first use
    and cached; None where neither works (:func:`unavailable_reason` says why).
    """
    name = "cuda-" + ("float64" if double else "float32")

    def load() -> ctypes.CDLL:
        given = os.environ.get(CUDA_LIBRARY_ENV)
        if given and not double:
            return _load(Path(given), double)
        missing = OSError(f"no nvcc found and ${CUDA_LIBRARY_ENV} not set")
        build = partial(build_cuda, double=double)
        return _from_cache(name, double, nvcc(), missing, build, " ".join(CUDA_FLAGS), str(double))

    return _once(name, load)


def unavailable_reason() -> str | None:
    """Why :func:`library` returned None (None when it loaded, or before it was asked)."""
    return _state.get("reason")  # type: ignore[return-value]


def scalar_check() -> str | None:
    """Compile the kernels' single-source functions for scalar lanes; None or the first complaint.

    Compiled with ``-DDK_SCALAR_CHECK``; a complaint from the compiler means a vector-only idiom
    crept into a ``DK_HD`` function.
    """
    compiler = _compiler()
    if compiler is None:
        return "no C++ compiler found (set CXX, or install g++ or clang++)"
    out = subprocess.run(
        [compiler, *SCALAR_CHECK_FLAGS, str(SOURCE)], capture_output=True, text=True, timeout=BUILD_TIMEOUT_S
    )
    return None if out.returncode == 0 else _complaint(out)

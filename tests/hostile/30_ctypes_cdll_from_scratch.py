"""Copy a shared object into scratch and load it with ctypes.CDLL (native code from a writable place).

Allowed by design: landlock's execute right covers execve, not mapping a readable file as code,
and ctypes already gives a program native calls. What contains native code is the same layer that
contains Python: seccomp, landlock, rlimits and the cgroup (exercised by 22, 23, 40, 41, 44-50)."""
import ctypes
import glob
import os
import shutil
import sys
import sysconfig

candidates = sorted(glob.glob(os.path.join(sysconfig.get_config_var("DESTSHARED") or "", "*.so")))
import _ctypes  # noqa: E402  (an extension module when the interpreter is not static)
candidates = [getattr(_ctypes, "__file__", "")] + candidates
candidates = [c for c in candidates if c and os.path.isfile(c)]
if not candidates:
    sys.exit("BLOCKED: no shared object found to copy")
for i, src in enumerate(candidates[:3]):
    dst = os.path.abspath(f"evil_{i}.so")
    try:
        shutil.copyfile(src, dst)
        ctypes.CDLL(dst)
        print(f"INFO: loaded native code from scratch ({dst}, copy of {src}); still confined")
        sys.exit(0)
    except OSError as e:
        print(f"BLOCKED: CDLL {dst} (copy of {src}): {e!r}")
sys.exit(1)

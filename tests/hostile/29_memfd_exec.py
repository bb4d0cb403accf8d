"""memfd_create an anonymous file, copy the python binary into it and fexecve it (fileless exec); contained = memfd_create killed or refused."""
import os
import sys

fd = os.memfd_create("r2g-hostile", 0)  # no MFD_CLOEXEC: the fd must survive the exec
print(f"ESCAPED: memfd_create returned fd {fd}", flush=True)
with open(os.path.realpath(sys.executable), "rb") as src:
    while chunk := src.read(1 << 20):
        os.write(fd, chunk)
os.execve(fd, ["r2g-hostile", "-I", "-S", "-c", "print('ESCAPED: fexecve of a memfd ran python')"], {})

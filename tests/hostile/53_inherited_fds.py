"""Hunt for leaked descriptors (writable files, directories usable with openat, network sockets); contained = nothing usable beyond 0-2 and the robo socket (exit 1)."""
import fcntl
import os
import socket
import stat
import sys

for fd in range(3, 1024):
    try:
        st = os.fstat(fd)
    except OSError:
        continue
    flags = fcntl.fcntl(fd, fcntl.F_GETFL)
    writable = (flags & os.O_ACCMODE) in (os.O_WRONLY, os.O_RDWR)
    kind = stat.filemode(st.st_mode)[0]
    print(f"INFO: fd {fd}: type {kind!r} mode {stat.filemode(st.st_mode)} writable={writable} ino={st.st_ino}")
    if stat.S_ISDIR(st.st_mode):
        try:
            new = os.open("r2g-hostile-canary-fd", os.O_CREAT | os.O_WRONLY, 0o600, dir_fd=fd)
            os.close(new)
            print(f"ESCAPED: created a file through inherited directory fd {fd}")
        except OSError as e:
            print(f"BLOCKED: openat via directory fd {fd}: {e!r}")
    elif stat.S_ISREG(st.st_mode) and writable:
        print(f"ESCAPED: inherited a writable regular file on fd {fd}")
    elif stat.S_ISSOCK(st.st_mode):
        with socket.socket(fileno=os.dup(fd)) as s:
            try:
                peer = s.getpeername()
            except OSError as e:
                peer = repr(e)
            print(f"INFO: fd {fd}: socket family {s.family!r} type {s.type!r} peer {peer!r}")
            if s.family in (socket.AF_INET, socket.AF_INET6):
                print(f"ESCAPED: inherited a network socket on fd {fd}")
sys.exit("BLOCKED: no usable leaked descriptor")

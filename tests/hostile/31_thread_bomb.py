"""Thread bomb capped at 2000 threads (small stacks, so the pids limit bites before address space); contained = thread creation fails early."""
import threading

threading.stack_size(256 * 1024)
stop = threading.Event()
started = 0
try:
    for _ in range(2000):
        threading.Thread(target=stop.wait, daemon=True).start()
        started += 1
except RuntimeError as e:
    print(f"BLOCKED: thread {started + 1} could not start: {e!r}")
    raise
finally:
    stop.set()
print(f"ESCAPED: started {started} threads, no pids limit")

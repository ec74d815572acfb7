"""What native code prints to file descriptors 1 and 2 during a block is collected (distinct lines, at most
MAX_LINES), nothing of it reaches the real descriptors, and blocks that print nothing or run after one that did
collect nothing (roadview_noise.native_output)."""

import os
import subprocess
import sys
import textwrap


def test_captured_output_collects_per_block_and_restores_the_descriptors(tmp_path):
    script = textwrap.dedent("""
        import os, sys
        from roadview_noise.native_output import MAX_LINES, captured_output
        with captured_output() as a:
            os.write(2, b"libpng warning: iCCP\\nlibpng warning: iCCP\\n")
            os.write(1, b"stdout line\\n")
            print("python print", flush=True)
        with captured_output() as b:
            pass
        with captured_output() as c:
            os.write(2, "".join(f"line {i}\\n" for i in range(3 * MAX_LINES)).encode())
        with captured_output(enabled=False) as d:
            pass
        os.write(2, b"after\\n")
        if os.fork() == 0:                          # a forked child makes its own buffer
            with captured_output() as e:
                os.write(2, b"child\\n")
            os.write(1, repr(e).encode() + b"\\n")
            os._exit(0)
        os.wait()
        with captured_output() as f:
            os.write(2, b"parent\\n")
        print(repr((a, b, len(c), c[0], d, f)))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert done.returncode == 0, done.stderr
    assert done.stderr == "after\n"
    child, parent = done.stdout.splitlines()
    assert child == "['child']"
    assert parent == repr((["libpng warning: iCCP", "stdout line", "python print"], [], 20, "line 0", [],
                           ["parent"]))

"""What native bindings print is captured per thread, and sys.stdout survives overlapping captures."""

from __future__ import annotations

import sys
import threading

from volcap_core.native_stderr import binding_prints


def test_overlapping_captures_in_threads_keep_their_own_text_and_restore_stdout(capsys):
    original = sys.stdout
    inside, release = threading.Barrier(3), threading.Barrier(3)
    seen: dict[int, str] = {}

    def capture(k: int) -> None:
        with binding_prints() as said:
            print(f"binding says {k}")
            inside.wait()   # both captures open at once
            release.wait()  # and closed in either order
        seen[k] = said.getvalue()

    threads = [threading.Thread(target=capture, args=(k,)) for k in (1, 2)]
    for t in threads:
        t.start()
    inside.wait()
    print("the main thread still prints")
    release.wait()
    for t in threads:
        t.join()
    assert seen == {1: "binding says 1\n", 2: "binding says 2\n"}
    assert sys.stdout is original
    assert capsys.readouterr().out == "the main thread still prints\n"

"""on_compute_thread: the main thread unless a thread marked itself (a Worker's sync thread)."""

import threading

from infinirl.runtime import compute_thread


def in_thread(fn):
    out = []
    thread = threading.Thread(target=lambda: out.append(fn()))
    thread.start()
    thread.join()
    return out[0]


def test_the_main_thread_computes_unless_another_thread_is_marked(monkeypatch):
    monkeypatch.setattr(compute_thread, "_compute_thread_ident", None)
    assert compute_thread.on_compute_thread()
    assert not in_thread(compute_thread.on_compute_thread)

    def mark_and_check():
        compute_thread.mark_compute_thread()
        return compute_thread.on_compute_thread()

    assert in_thread(mark_and_check)
    assert not compute_thread.on_compute_thread()  # the main thread is no longer it

"""The pool worker's pipe protocol (service.worker.serve_pipe) with a fake runtime, in a thread."""
import multiprocessing
import threading

import pytest

import service.runtime
from service.config import Settings
from service.worker import serve_pipe


class FakeRuntime:
    def run_batch(self, requests):
        return [f"draped {r}" for r in requests]

    def run_job(self, request, progress):
        for done in range(1, 4):
            if progress(done, 3):
                return None
        raise AssertionError("the job should have been stopped")


@pytest.fixture
def worker(monkeypatch):
    monkeypatch.setattr(service.runtime.Runtime, "load", classmethod(lambda cls, settings: FakeRuntime()))
    parent, child = multiprocessing.Pipe()
    thread = threading.Thread(target=serve_pipe, args=(child, Settings()), daemon=True)
    thread.start()
    assert parent.recv()[0] == "ready"
    yield parent, thread
    if thread.is_alive():
        parent.send(None)
        thread.join(5)


def test_stray_messages_are_ignored(worker):
    parent, thread = worker
    parent.send(True)  # e.g. a late progress answer
    parent.send(("drape", ["a", "b"]))
    assert parent.recv() == ("done", ["draped a", "draped b"])
    assert thread.is_alive()


def test_stop_during_a_job_exits_without_reporting_it(worker, tmp_path):
    parent, thread = worker
    parent.send(("job", "request", str(tmp_path / "result.glb")))
    assert parent.recv() == ("progress", 1, 3)
    parent.send(None)  # the pool stops while the job runs
    thread.join(5)
    assert not thread.is_alive()
    assert not parent.poll(0.2)  # no "done": the job stays leased and is run again after the restart
    assert not (tmp_path / "result.glb").exists()

"""sim_data.parts: a job spread over processes, one per GPU or CPU core."""

import os
import shutil
import sys
import threading
import time

import pytest

from sim_data.parts import exclusive, in_turn, local_cores, local_gpus, parse_part, run_parallel, take


def test_parts_cover_the_work_once():
    assert parse_part("1/3") == (1, 3) and parse_part(None) is None
    items = list(range(10))
    shares = [take(items, (k, 3)) for k in range(3)]
    assert shares == [[0, 3, 6, 9], [1, 4, 7], [2, 5, 8]] and take(items, None) == items
    for bad in ("3/3", "-1/2", "1", "a/b"):
        with pytest.raises(ValueError, match="K/N"):
            parse_part(bad)


def test_processes_get_one_gpu_each_and_a_failure_names_its_log(tmp_path, monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,7")
    assert local_gpus() == ["4", "7"]
    write = "import os, sys; open(sys.argv[1], 'w').write(os.environ['CUDA_VISIBLE_DEVICES'])"
    outs = [tmp_path / f"gpu{i}" for i in range(3)]
    run_parallel([[sys.executable, "-c", write, str(o)] for o in outs], ["4", "7"], tmp_path / "logs")
    seen = [o.read_text() for o in outs]
    assert sorted(seen[:2]) == ["4", "7"] and seen[2] in ("4", "7")  # the third waits for a free GPU
    fail = "import sys; print('the reason'); sys.exit(3)"
    with pytest.raises(RuntimeError, match=r"(?s)1 of 2 processes failed; part 1 exited with 3.*the reason"):
        run_parallel([[sys.executable, "-c", "pass"], [sys.executable, "-c", fail]], ["0", "1"], tmp_path / "logs")


@pytest.mark.skipif(not shutil.which("taskset") or not hasattr(os, "sched_getaffinity"), reason="needs taskset")
def test_processes_on_cpu_cores_are_pinned_one_to_each_and_see_no_gpu(tmp_path, monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")
    cores = local_cores()
    assert cores == [str(c) for c in sorted(os.sched_getaffinity(0))]
    write = ("import os, sys; open(sys.argv[1], 'w').write(repr((sorted(os.sched_getaffinity(0)), "
             "os.environ['CUDA_VISIBLE_DEVICES'])))")
    outs = [tmp_path / f"core{i}" for i in range(len(cores))]
    run_parallel([[sys.executable, "-c", write, str(o)] for o in outs], cores, tmp_path / "logs", on="cpu")
    assert sorted(o.read_text() for o in outs) == sorted(repr(([int(c)], "")) for c in cores)
    with pytest.raises(ValueError, match="'gpu' or 'cpu'"):
        run_parallel([[sys.executable, "-c", "pass"]], cores, tmp_path / "logs", on="tpu")


def test_in_turn_takes_what_no_other_holds_first_and_keeps_the_order(tmp_path):
    done = []

    def attempt(i, wait):
        with exclusive(tmp_path / f"{i}.lock", wait) as held:
            if not held:
                return None
            done.append(i)
            return 10 * i

    got = []
    with exclusive(tmp_path / "0.lock"):  # another process works on item 0
        worker = threading.Thread(target=lambda: got.extend(in_turn(list(range(6)), attempt)))
        worker.start()
        for _ in range(600):
            if len(done) == 5:
                break
            time.sleep(0.05)
        assert done == [1, 2, 3, 4, 5] and not got and worker.is_alive()  # then it waits for item 0
    worker.join(30)
    assert done == [1, 2, 3, 4, 5, 0] and got == [0, 10, 20, 30, 40, 50]
    assert in_turn([], attempt) == []

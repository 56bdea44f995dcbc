"""torch's thread count shared between Python threads (nap3d_graph.torch_threads)."""

import threading
import time

import torch

from nap3d_graph.torch_threads import torch_threads


def _restore_after(test):
    def wrapped():
        before = torch.get_num_threads()
        try:
            test()
        finally:
            torch.set_num_threads(before)

    return wrapped


@_restore_after
def test_blocks_of_one_count_overlap_and_keep_it_until_the_last_leaves():
    """Two threads asking for one thread are inside at once (neither waits for the other), each
    sees one thread for its whole block although the first leaves while the second is inside,
    and the count from before comes back after the last."""
    torch.set_num_threads(2)
    inside = threading.Barrier(2, timeout=10)
    first_left = threading.Event()
    seen = {}

    def first():
        with torch_threads(1):
            inside.wait()  # both inside: blocks of one count do not exclude each other
            seen["first"] = torch.get_num_threads()
        first_left.set()

    def second():
        with torch_threads(1):
            inside.wait()
            first_left.wait(10)
            seen["second_after_first_left"] = torch.get_num_threads()

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert seen == {"first": 1, "second_after_first_left": 1}
    assert torch.get_num_threads() == 2


@_restore_after
def test_a_block_of_another_count_waits_for_the_open_ones():
    torch.set_num_threads(3)
    order = []
    opened = threading.Event()

    def holder():
        with torch_threads(1):
            opened.set()
            time.sleep(0.3)
            order.append(("holder", torch.get_num_threads()))

    def other():
        opened.wait(10)
        with torch_threads(2):
            order.append(("other", torch.get_num_threads()))

    threads = [threading.Thread(target=holder), threading.Thread(target=other)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert order == [("holder", 1), ("other", 2)]
    assert torch.get_num_threads() == 3


@_restore_after
def test_nested_blocks_on_one_thread_do_not_wait_for_themselves():
    torch.set_num_threads(2)
    with torch_threads(1):
        with torch_threads(3):
            assert torch.get_num_threads() == 3
        with torch_threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with torch_threads(None):  # None leaves torch's setting alone
        assert torch.get_num_threads() == 2

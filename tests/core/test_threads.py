"""lab.core.threads.single_threaded: one torch thread inside, the caller's count restored after."""

import torch

from lab.core.threads import single_threaded


def test_one_thread_inside_and_the_count_restored_after_nested_blocks():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with single_threaded():
            assert torch.get_num_threads() == 1
            with single_threaded():
                assert torch.get_num_threads() == 1
            assert torch.get_num_threads() == 1  # the inner block leaves the outer one's setting
        assert torch.get_num_threads() == 2
        with single_threaded(False):
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)

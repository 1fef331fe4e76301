"""The results store's access: sweeps of different configurations hold them together, one of the same is refused
(tests/evaluation/test_sweep.py has it across processes)."""

from __future__ import annotations

import os

import pytest

from svs_torch.core.checks import InputError
from svs_torch.evaluation.store import ResultStore
from svs_torch.evaluation.store_access import sweep_is_writing

OFD_LOCKS = os.name == "posix" and hasattr(__import__("fcntl"), "F_OFD_SETLK")


@pytest.mark.skipif(not OFD_LOCKS, reason="needs open-file-description locks (Linux)")
def test_claims_of_other_configurations_are_taken_beside_and_the_same_refused(tmp_path):
    db = tmp_path / "store.sqlite"
    with ResultStore(db) as first, ResultStore(db) as second, ResultStore(db) as third:
        first.claim_for_a_sweep(["a", "b"])
        second.claim_for_a_sweep(["c"])  # another grid: no refusal
        with pytest.raises(InputError, match=f"^db: another sweep is writing {db} and running 1 of this sweep's 2 "
                                             r"configurations; run this one once it has ended \(it then runs only"):
            third.claim_for_a_sweep(["d", "b"])
        assert sweep_is_writing(db)
        first.close()
        third.claim_for_a_sweep(["d", "b"])  # released with the store
    assert not sweep_is_writing(db)

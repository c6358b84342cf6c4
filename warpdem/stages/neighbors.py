"""Skinned candidate lists (host side): the scratch arrays and launches of a rebuild, for every kind of list of
:mod:`warpdem.kernels.neighbors` (the sphere–sphere list of warpdem.stages.contact, the sphere–face and node–face lists
of warpdem.stages.fem_contact).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import warp as wp

from ..kernels import neighbors as kn


def make_struct(cls: Any, **fields: Any) -> Any:
    """An instance of the wp.struct ``cls`` with the given fields (a wp.struct's constructor takes no arguments)."""
    value = cls()
    for name, field in fields.items():
        setattr(value, name, field)
    return value


@dataclasses.dataclass
class SlotArrays:
    """The arrays of one skinned list.

    Attributes:
        count: candidates per owner, shape (owner_capacity,), int32; may exceed K (then only K slots are filled).
        index: candidate per slot, shape (owner_capacity * K,), int32.
        history: the per-slot history arrays, an instance of the list's ``ListSpec.history`` struct (None for a list
            without history).
    """

    count: wp.array
    index: wp.array
    history: Any = None


class SkinnedList:
    """One skinned list of a Model/State pair: its kernels and, for a list with history, the scratch arrays that a
    rebuild fills before it commits them over the state's list.

    Args:
        kernels: the list's kernels (``make_list_kernels``).
        owners: owner capacity, the threads of a rebuild.
        max_slots: slots per owner, K.
        device: where the arrays live.
        history: name → dtype of each history array (the fields of ``ListSpec.history``); None for a list without.
    """

    def __init__(
        self,
        kernels: kn.ListKernels,
        owners: int,
        max_slots: int,
        device: wp.context.Device,
        history: dict[str, Any] | None = None,
    ) -> None:
        if (history is None) != (kernels.commit is None):
            raise ValueError("history arrays are given exactly for a list with history (a commit kernel)")
        self.kernels = kernels
        self.owners = owners
        self.max_slots = max_slots
        self.device = device
        self.no_history = kernels.spec.history() if history is None else None
        self.new: SlotArrays | None = None
        if history is not None:
            slots = owners * max_slots
            arrays = {name: wp.zeros(slots, dtype=dtype, device=device) for name, dtype in history.items()}
            self.new = SlotArrays(
                wp.zeros(owners, dtype=int, device=device),
                wp.zeros(slots, dtype=int, device=device),
                make_struct(kernels.spec.history, **arrays),
            )

    def rebuild(
        self,
        inputs: Any,
        grid: wp.HashGrid,
        owner_count: wp.array,
        owner_q: wp.array,
        candidate_count: wp.array,
        lists: SlotArrays,
        needed: wp.array,
    ) -> None:
        """Rebuild the state's lists (launches only: usable inside a graph capture).

        Args:
            inputs: the candidate test's arrays, an instance of the list's ``ListSpec.inputs`` struct.
            grid: the hash grid of the candidates, built.
            owner_count: live owners, shape (1,).
            owner_q: the owners' positions [m].
            candidate_count: live candidates, shape (1,).
            lists: the state's lists, rebuilt in place.
            needed: the largest count seen, shape (1,) (raised, never lowered).
        """
        new = self.new
        if new is None:  # a list without history is built in place
            lists = new = SlotArrays(lists.count, lists.index, self.no_history)
        wp.launch(
            self.kernels.build,
            dim=self.owners,
            inputs=[
                # Model:
                self.max_slots,
                # In:
                inputs,
                # State in:
                grid.id,
                owner_count,
                owner_q,
                candidate_count,
                lists.count,
                lists.index,
                lists.history,
            ],
            outputs=[new.count, new.index, new.history, needed],
            device=self.device,
        )
        if self.kernels.commit is not None:
            wp.launch(
                self.kernels.commit,
                dim=self.owners,
                inputs=[self.max_slots, owner_count, new.count, new.index, new.history],
                outputs=[lists.count, lists.index, lists.history],
                device=self.device,
            )


def finish_rebuild(
    owner_count: wp.array,
    owner_q: wp.array,
    q_at_build: wp.array,
    rebuild_flag: wp.array,
    rebuild_total: wp.array,
    device: wp.context.Device,
) -> None:
    """After a rebuild: keep the owners' positions to measure the skin from, lower the flag, count the rebuild
    (launch only). ``owner_q`` sets the threads: one per owner slot."""
    wp.launch(
        kn.FINISH_REBUILD_KERNELS[owner_q.dtype],
        dim=max(owner_q.shape[0], 1),
        inputs=[owner_count, owner_q],
        outputs=[q_at_build, rebuild_flag, rebuild_total],
        device=device,
    )

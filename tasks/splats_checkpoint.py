"""The splats step's training checkpoint in the store (`splats_checkpoint/`): written every
`checkpoint_every_iters`, read back when the same training is run again after a kill."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from wonderverse.schema import SPLATS_CHECKPOINT
from wonderverse.store import SceneStore, cache_key, write_array

log = logging.getLogger("wonderverse.splats")
CHECKPOINT = SPLATS_CHECKPOINT.path
CHECKPOINT_VERSION = 2  # 2: plain tensors and JSON (1 was a pickle)


def save_checkpoint(store: SceneStore, key: str, step: int, state: dict[str, Any]) -> None:
    """The training state as plain tensors (one byte blob) and JSON (the `layout` attribute): never a pickle,
    so a scene folder cannot run code when its checkpoint is read back."""
    from wonderverse.splats.checkpoint import pack

    blob, layout = pack(state)
    ckpt_key = cache_key("checkpoint", CHECKPOINT_VERSION, {"step": step}, [key])
    with store.staged(CHECKPOINT, ckpt_key, step=step, run_key=key, layout=layout) as g:
        write_array(g, CHECKPOINT.state, np.frombuffer(blob, np.uint8))


def load_checkpoint(store: SceneStore, key: str, device: Any, n_views: int, sh_rest: int) -> dict[str, Any] | None:
    """The training state saved for this run (`key`), else None. A checkpoint of an older format, a damaged
    one or one whose layout is not the trainer's state is ignored with one warning: training starts over."""
    from wonderverse.splats.checkpoint import blob_size, check_train_state, unpack

    try:
        a = store.meta(CHECKPOINT)
        if a is None or a.run_key != key:
            return None
        if store.cache_key_of(CHECKPOINT) != cache_key("checkpoint", CHECKPOINT_VERSION, {"step": a.step}, [key]):
            raise ValueError("written by another version")
        size = blob_size(a.layout)
        arr = store.group(CHECKPOINT)["state"]
        if arr.dtype != np.uint8 or arr.shape != (size,):  # checked before reading: a crafted shape is not read
            raise ValueError(f"its state array is {arr.dtype} {arr.shape}, the layout needs uint8 ({size},)")
        state = unpack(store.array(CHECKPOINT.state).tobytes(), a.layout, device)
        check_train_state(state, n_views, sh_rest)
        if state["step"] != a.step:
            raise ValueError(f"its state is at step {state['step']}, its attributes say {a.step}")
    except Exception as e:  # a checkpoint is only a cache: whatever is wrong with it, train from the start
        reason = " ".join(f"{type(e).__name__}: {e}".split())
        log.warning("ignoring the splat training checkpoint (%s); training starts from the beginning", reason[:300])
        return None
    log.warning("resuming splat training from the checkpoint at step %d", a.step)
    return state

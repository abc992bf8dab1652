"""``safenav convert``: an older safenav's checkpoint rewritten so that it loads without pickle."""

from __future__ import annotations

from pathlib import Path

import tyro

from safenav.cli import app


@app.command(name="convert")
def convert(
    checkpoint: tyro.conf.Positional[Path],
    out: Path | None = None,
    trust_pickle: bool = False,
) -> None:
    """Rewrite a checkpoint that safenav refuses to load because it needs pickle ("needs pickle
    to load ... safenav convert PATH"), in the form that ``eval``, ``export``, ``fly``,
    ``average``, ``render`` and ``train --resume`` read without unpickling.

    Checkpoints of an older safenav (a training ``checkpoint.pt``: its NumPy RNG state) are read
    with NumPy arrays allowed besides tensors, still without running any code of the file; the
    result holds the same values (the RNG state as tensors), so ``--resume`` continues exactly.
    A file that asks for anything else is refused (no safenav wrote it) unless
    ``--trust-pickle``. docs/reliability.md, "Safe checkpoints".

    Args:
        checkpoint: The checkpoint file (or a run directory: its checkpoint.pt).
        out: Where to write the converted checkpoint (default: replace CHECKPOINT, atomically).
        trust_pickle: Unpickle CHECKPOINT in full: only for a file you trust and whose origin you
            know, since unpickling runs whatever code the file holds.
    """
    from safenav.common.checkpoint import convert_checkpoint
    from safenav.common.checks import check_output_file

    if out is not None:
        check_output_file(out, "--out", "checkpoint.pt")
    else:  # replaced in place: it must be writable
        target = checkpoint / "checkpoint.pt" if checkpoint.is_dir() else checkpoint
        if target.is_file():
            check_output_file(target, "CHECKPOINT", "checkpoint.pt")
    src, dst, how = convert_checkpoint(checkpoint, out, trust_pickle=trust_pickle)
    if how == "safe" and dst.resolve() == src.resolve():
        print(f"{src} already loads without pickle: nothing to convert")
        return
    read = {"safe": "it loaded without pickle already", "numpy": "NumPy arrays as tensors",
            "pickle": "unpickled in full (--trust-pickle)"}[how]  # fmt: skip
    print(f"wrote {dst}: {src} in the form safenav loads without pickle ({read})")

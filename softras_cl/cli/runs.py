"""What the fitting commands share around a fit: option names in errors, late interrupts, the summary."""
from __future__ import annotations

import contextlib
import sys
from typing import Iterator

from softras_cl.errors import InputError
from softras_cl.interrupts import Caught, first_interrupt_calls


@contextlib.contextmanager
def named_as_options(options: dict[str, str]) -> Iterator[None]:
    """Reword a configuration's InputError ("fov_deg must be ...") with the command's option for
    that field ("--fov must be ..."); ``options`` maps field names to option names."""
    try:
        yield
    except InputError as e:
        field, _, rest = str(e).partition(" ")
        if field not in options:
            raise
        raise InputError(f"{options[field]} {rest}") from None


def _say_finishing(signum: int) -> None:
    print("softras-cl: interrupted; writing the outputs first (interrupt again to stop at once: "
          "every file already written stays complete)", file=sys.stderr)


@contextlib.contextmanager
def finishing_outputs() -> Iterator[Caught]:
    """A first Ctrl-C/SIGTERM while the outputs are written is noted (``caught.signum``) and the
    writing goes on; a second one stops at once."""
    with first_interrupt_calls(_say_finishing) as caught:
        yield caught


def run_state(interrupted: bool) -> str:
    """How the summary line describes the run."""
    if interrupted:
        return "interrupted; outputs are from the best values so far (--resume continues the fit)"
    return "done"

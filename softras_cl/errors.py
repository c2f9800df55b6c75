"""The errors softras-cl raises for things a user can fix, and the exit code of each.

Every class derives from the built-in exception a caller would already catch (ValueError for bad
input, OSError for files, MemoryError for sizes), so ``except ValueError`` keeps working. The
command line turns each into one line on stderr and its ``exit_code``; docs/reliability.md has
the table.
"""
from __future__ import annotations

__all__ = ["SoftrasError", "InputError", "OutputError", "DeviceError", "ResourceError",
           "ResultError", "EXIT_OK", "EXIT_RESULT", "EXIT_INPUT", "EXIT_OUTPUT", "EXIT_RESOURCE",
           "EXIT_INTERNAL", "EXIT_INTERRUPTED"]

EXIT_OK = 0             # done, and the result is valid
EXIT_RESULT = 1         # ran to the end, but the result is not valid (NaN metrics, degenerate scene)
EXIT_INPUT = 2          # bad option, argument or input file; nothing was computed
EXIT_OUTPUT = 3         # the output folder or file cannot be used (locked, not writable, disk full)
EXIT_RESOURCE = 4       # no usable OpenCL device, or the request does not fit its memory
EXIT_INTERNAL = 70      # a bug in softras-cl (EX_SOFTWARE): -vv shows the traceback
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM; what was finished is kept (128 + SIGINT)


class SoftrasError(Exception):
    """Base of the errors below; ``exit_code`` is what the command line exits with."""
    exit_code = EXIT_INTERNAL


class InputError(SoftrasError, ValueError):
    """An argument, option or input file is not what was expected (the message names it)."""
    exit_code = EXIT_INPUT


class OutputError(SoftrasError, OSError):
    """An output folder or file cannot be written; earlier results there are left unchanged."""
    exit_code = EXIT_OUTPUT


class DeviceError(SoftrasError, RuntimeError):
    """No OpenCL platform or device, or none that matches the user's choice."""
    exit_code = EXIT_RESOURCE


class ResourceError(SoftrasError, MemoryError):
    """The request needs more memory than the device or the machine has (the message says how
    much it needs and what is available)."""
    exit_code = EXIT_RESOURCE


class ResultError(SoftrasError, RuntimeError):
    """The computation ran but its result is not valid (non-finite metrics, empty render)."""
    exit_code = EXIT_RESULT

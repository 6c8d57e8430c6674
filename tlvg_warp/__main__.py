import sys

from .warmup import leave, start_cuda_warmup

start_cuda_warmup(sys.argv[1:])  # before the imports below bring torch in: the two overlap

from .cli import main  # noqa: E402

leave(main(), sys.argv[1:])  # after a GPU command, without the interpreter's teardown

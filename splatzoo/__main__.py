"""`python -m splatzoo` (and `torchrun -m splatzoo train ...`) runs the command line."""
from .cli import main

main()

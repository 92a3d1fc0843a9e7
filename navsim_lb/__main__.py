"""`python -m navsim_lb`: the `navsim-lb` command where its console script is not on the PATH."""

from navsim_lb.cli import main

main()

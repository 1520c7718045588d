"""`python -m flows ARGS` is `wonderverse ARGS`: the supervising parent (flows.supervise), which starts the command
itself in a child (`python -m flows.cli`) and imports nothing of it, so that it starts in a few milliseconds."""

from flows.supervise import main

main()

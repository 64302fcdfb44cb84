"""``python -m lolgps_torch COMMAND [FLAGS]``: the ``lolgps`` command."""

from lolgps_torch.commands.lolgps import main

if __name__ == "__main__":
    main()

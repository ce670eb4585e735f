"""`python -m ctgs ...` is the `ctgs` command."""

from ctgs.cli import main

if __name__ == "__main__":
    main()

"""`python -m ptovs` runs the command line."""

from ptovs.cli import main

if __name__ == "__main__":
    main()

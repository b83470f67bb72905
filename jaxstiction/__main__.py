import sys

from ._cli import main


if __name__ == "__main__":  # importing the module (as the docs build does) runs nothing
    sys.exit(main())

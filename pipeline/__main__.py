import sys

from pipeline.app.cli import main

if __name__ == "__main__":  # not when a spawned process (the mapping process) imports it
    sys.exit(main())

"""python -m identification_node VERB ..."""
import sys

from .cli import main

sys.exit(main())

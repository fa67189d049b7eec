"""python -m identification_node VERB ..."""
import sys

from .programs import identification_cli

sys.exit(identification_cli())

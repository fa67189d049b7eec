"""python -m identification_node VERB ..."""
import sys

from identification_node.programs import identification_cli

sys.exit(identification_cli())

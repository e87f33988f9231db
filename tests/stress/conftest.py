import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(__file__)))  # reference.py and helpers live in tests/

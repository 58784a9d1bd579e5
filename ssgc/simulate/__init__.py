"""Physics on exported scenes: settling to static stability (`settle.py`, MuJoCo)."""

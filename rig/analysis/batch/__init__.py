"""Many curves, one analysis each (`rig analyze --each`): the units of work and their runner,
serial, in processes or on Dask (`engine`), the command and its Python API (`each`), the table
and its journal (`table`), each curve's quality rating (`quality`) and the map's pictures
(`map_report`).

The top layer of the analysis.
"""

"""Device links of the cell (thesis Ch. 2, Fig. 2-5).

* :mod:`icefab.cell.valve` -- the valve microcontroller (``firmware/PROTOCOL.md``), frames
  in :mod:`icefab.cell.valve_frames`.
"""

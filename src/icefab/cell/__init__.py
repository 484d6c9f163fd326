"""Device links of the cell (thesis Ch. 2, Fig. 2-5) and a virtual cell behind them.

The control PC talks to three devices; real-time signals come only from the robot
controller (thesis 2.3):

* :mod:`icefab.cell.robot_protocol`, :mod:`icefab.cell.robot` -- the Adept C40 running
  the V+ server that :mod:`icefab.cell.vplus` writes (TCP socket; constant-dt paths,
  triggers on digital outputs, completion reported by sequence number).
* :mod:`icefab.cell.valve` -- the valve microcontroller (``firmware/PROTOCOL.md``).
* :mod:`icefab.cell.laser` -- the Keyence LK-G laser controller (RS-232, ASCII, CR);
  :mod:`icefab.cell.laser_emulator` emulates the subset used.
* :mod:`icefab.cell.virtual` -- ``icefab cell serve``: a virtual robot, the valve
  firmware's host build and the laser emulator in one process, depositing with
  :mod:`icefab.sim`.
"""

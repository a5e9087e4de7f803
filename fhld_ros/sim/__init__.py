"""Synthetic LiDAR road scenes with ground truth (`fhld simulate`).

Modules, from the world to the sensor:
  road.py       reference line: plan curve, grade, vertical curves, crossfall over s
  layout.py     lanes, shoulders, gores and topology events -> painted lane lines
  markings.py   paint lookup (dash patterns, wear) and distractor stencils; GT polylines
  scene.py      analytic ground height and material
  ground_grid.py  the cached heightfield tiles (a camera builds those under its sector)
  obstacles.py  buildings, vegetation, poles, barriers, traffic
  ego.py        speed, lane following and lane changes, sensor poses, odometry drift
  raycast.py    vectorised ray casting against ground and obstacles
  lidar.py      sensor presets, return/intensity model, driver point layouts
  simulator.py  the public API (Simulator, Sweep, Scene)
  gt_lines.py   GT polylines cut to the window square or a disc around the car
  simulate.py   the CLI command (bag + preview); preview.py draws the picture
"""

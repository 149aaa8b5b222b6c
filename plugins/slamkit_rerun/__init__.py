"""slamkit_rerun: a live viewer of a run on the lifecycle hooks, with rerun (https://rerun.io).

``slamkit run +viewer=rerun`` opens rerun's viewer and streams the run to it; ``viewer.save=FILE.rrd`` records to a
file without a display. The plugin only listens to events (slamkit/events.py): it never touches the map or the
pipeline, and a failure of the viewer is logged and ends the viewing, never the run. Needs ``rerun-sdk`` (the
optional extra ``slamkit[viewer]``).
"""

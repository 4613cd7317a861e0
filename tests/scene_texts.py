"""Scene files that tests in several folders render: one room, each test's objects inside it.

Tests import this module by name (`from scene_texts import lit_room`): pytest puts `tests/` on
the import path for every test package below it."""


def lit_room(objects: str, *, width: int, height: int, f: float, cx: float, cy: float, max_bounces: int,
             fps: float | None = None) -> str:
    """TOML of a 1 m box room, open towards the camera (1.8 m away, looking slightly down), lit by
    a 0.3 m square light under its ceiling; `objects` ([[objects]] tables) are added inside.
    The room's own text has no braces, so `objects` may hold `str.format` fields for the caller."""
    fps_line = "" if fps is None else f"fps = {fps}\n"
    return f"""
[render]
width = {width}
height = {height}
max_bounces = {max_bounces}
{fps_line}
[camera]
fx = {f}
fy = {f}
cx = {cx}
cy = {cy}
position = [0.0, 0.5, 1.8]
look_at = [0.0, 0.4, 0.0]

[[objects]]
name = "room"
shape = "box"
size = [1.0, 1.0, 1.0]
position = [0.0, 0.5, 0.0]
open = ["+z"]
albedo = [0.7, 0.6, 0.5]

[[objects]]
name = "light"
shape = "quad"
size = [0.3, 0.3]
position = [0.0, 0.99, 0.0]
rotation = [180.0, 0.0, 0.0]
albedo = 0.0
emission = [10.0, 10.0, 10.0]
{objects}"""

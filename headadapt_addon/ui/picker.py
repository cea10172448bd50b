"""Modal landmark picking in the 3D viewport, with points and labels drawn by the gpu module.

Click: place the selected FDP where the mouse ray hits the scan, then select the next missing one.
Ctrl-click: remove the nearest FDP. M: place the selected FDP at its mirror suggestion.
Right-click or Esc: finish. Clicks and keys over the sidebar, a header or another editor pass through
to them. The placement logic lives in landmarks.py (tested headless).
"""

import bpy
import numpy as np

from ..blender import landmarks
from ..core import mpeg4

_draw_handles = []


def _colours():
    return {"placed": (0.2, 0.5, 1.0, 1.0), "active": (1.0, 0.85, 0.1, 1.0),
            "suggested": (1.0, 0.4, 0.9, 1.0), "template": (0.3, 1.0, 0.4, 1.0),
            "flagged": (1.0, 0.15, 0.1, 1.0)}       # a click the last fit judged wrong (landmarks.get_flagged)


def draw_landmarks_3d():
    """Draw the scan's landmarks (and suggestions, and the active FDP on the template) as points."""
    import gpu
    from gpu_extras.batch import batch_for_shader

    context = bpy.context
    s = getattr(context.scene, "headadapt", None)
    if s is None or s.scan is None:
        return
    col = _colours()
    groups = {"placed": [], "active": [], "suggested": [], "template": [], "flagged": []}
    local = landmarks.get_landmarks(s.scan)
    pts = landmarks.world_points(s.scan, local)
    flagged = landmarks.get_flagged(s.scan, local)
    for k, p in pts.items():
        groups["active" if k == s.active_fdp else "flagged" if k in flagged else "placed"].append(p)
    groups["suggested"] = list(landmarks.world_points(
        s.scan, landmarks.get_landmarks(s.scan, landmarks.SUGGESTED_PROP)).values())
    if s.template_root is not None:
        for o in s.template_root.children_recursive:
            if o.get("headadapt_fdp") == s.active_fdp:
                groups["template"].append(np.array(o.matrix_world.translation))
    try:
        shader = gpu.shader.from_builtin("POINT_UNIFORM_COLOR")
    except ValueError:                   # Blender before 4.0 (Debian's 3.4): points from the plain shader
        shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    gpu.state.point_size_set(9.0)
    gpu.state.depth_test_set("LESS_EQUAL")
    for name, ps in groups.items():
        if not ps:
            continue
        batch = batch_for_shader(shader, "POINTS", {"pos": [tuple(map(float, p)) for p in ps]})
        shader.uniform_float("color", col[name])
        batch.draw(shader)
    gpu.state.depth_test_set("NONE")
    gpu.state.point_size_set(1.0)


def draw_labels_2d():
    """Draw the FDP ids next to their points: only where the view sees the point (not through the
    head) and thinned so no two labels overlap (the active FDP and the 8 clicks first)."""
    import blf
    from bpy_extras.view3d_utils import location_3d_to_region_2d

    context = bpy.context
    s = getattr(context.scene, "headadapt", None)
    if s is None or s.scan is None or context.region_data is None:
        return
    local = landmarks.get_landmarks(s.scan)
    pts = landmarks.world_points(s.scan, local)
    screen = {}
    for k, p in pts.items():
        xy = location_3d_to_region_2d(context.region, context.region_data, p)
        if xy is not None:
            screen[k] = (xy[0], xy[1])
    eye = np.array(context.region_data.view_matrix.inverted().translation)
    if not context.region_data.is_perspective:      # orthographic: look from far along the view
        centre = np.mean(list(pts.values()), axis=0) if pts else eye
        back = np.array(context.region_data.view_matrix.inverted().to_3x3().col[2])
        eye = centre + back * 10.0 * float(max(s.scan.dimensions))
    seen = landmarks.seen_from(s.scan, {k: local[k] for k in screen}, eye)
    flagged = landmarks.get_flagged(s.scan, local)
    for k in landmarks.thinned({k: xy for k, xy in screen.items() if seen[k]}, first=(s.active_fdp,)):
        xy = screen[k]
        blf.size(0, 13 if k == s.active_fdp else 11)
        blf.color(0, *(_colours()["active"] if k == s.active_fdp else _colours()["flagged"] if k in flagged
                       else (1, 1, 1, 1)))
        blf.position(0, xy[0] + 6, xy[1] + 4, 0)
        blf.draw(0, k)


def add_draw_handlers():
    """Install the viewport overlay (once)."""
    if not _draw_handles:
        _draw_handles.append(bpy.types.SpaceView3D.draw_handler_add(draw_landmarks_3d, (), "WINDOW", "POST_VIEW"))
        _draw_handles.append(bpy.types.SpaceView3D.draw_handler_add(draw_labels_2d, (), "WINDOW", "POST_PIXEL"))


def remove_draw_handlers():
    while _draw_handles:
        handle = _draw_handles.pop()
        try:
            bpy.types.SpaceView3D.draw_handler_remove(handle, "WINDOW")
        except ValueError:
            pass


def mouse_ray(context, event):
    """World-space (origin, direction) of the mouse ray in the 3D region."""
    from bpy_extras import view3d_utils

    coord = (event.mouse_region_x, event.mouse_region_y)
    origin = view3d_utils.region_2d_to_origin_3d(context.region, context.region_data, coord)
    direction = view3d_utils.region_2d_to_vector_3d(context.region, context.region_data, coord)
    return np.array(origin), np.array(direction)


def over_view(area, event):
    """Whether the mouse (window coordinates) is over the 3D view itself: inside the area and not over
    one of the regions drawn over the view (the sidebar, the toolbar, the headers, the last operator's
    panel). A modal operator hears every click in the window first: a click meant for the sidebar's
    FDP list would place the FDP behind it, and the list would never hear it."""
    x, y = event.mouse_x, event.mouse_y

    def inside(r):
        return r.x <= x < r.x + r.width and r.y <= y < r.y + r.height

    if area is None or not inside(area):
        return False
    return not any(r.type != "WINDOW" and r.width > 1 and r.height > 1 and inside(r) for r in area.regions)


class HEADADAPT_OT_pick_landmarks(bpy.types.Operator):
    """Click FDPs on the scan: click places the selected FDP and moves to the next missing one, Ctrl-click removes, Ctrl-Z undoes a click, M mirrors, Esc ends"""
    bl_idname = "headadapt.pick_landmarks"
    bl_label = "Pick Landmarks"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        s = context.scene.headadapt
        if s.scan is None:
            why = "No scan selected: pick the scan object in the Scan panel"
        elif s.scan.type != "MESH" or len(s.scan.data.polygons) == 0:
            why = f"The scan {s.scan.name!r} has no faces to click on"
        elif context.area is None or context.area.type != "VIEW_3D":
            why = "Picking works in a 3D view: press it from the 3D view's sidebar"
        else:
            return True
        cls.poll_message_set(why)
        return False

    def status(self, context):
        """The status bar says which FDP the next click places (after every click, not only the first)."""
        k = context.scene.headadapt.active_fdp
        hint = f" {mpeg4.CLICK_HINTS[k]}" if k in mpeg4.CLICK_HINTS else ""
        context.workspace.status_text_set(f"HeadAdapt: click to place {k} ({mpeg4.FDPS[k].label}){hint}, Ctrl-click "
                                          "removes, Ctrl-Z undoes a click, M mirrors the partner, "
                                          "Esc/right-click ends")

    def invoke(self, context, event):
        add_draw_handlers()
        context.window_manager.modal_handler_add(self)
        self.done, self.undone = [], []         # this session's changes: (clicks, suggestions, FDP) before each
        self.status(context)
        return {"RUNNING_MODAL"}

    def snapshot(self, s):
        sug = landmarks.SUGGESTED_PROP
        return (landmarks.get_landmarks(s.scan), landmarks.get_landmarks(s.scan, sug) if sug in s.scan else None,
                s.active_fdp)

    def restore(self, s, state):
        pts, sug, active = state
        landmarks.set_landmarks(s.scan, pts)
        if sug is not None:
            landmarks.set_landmarks(s.scan, sug, prop=landmarks.SUGGESTED_PROP)
        elif landmarks.SUGGESTED_PROP in s.scan:
            del s.scan[landmarks.SUGGESTED_PROP]
        s.active_fdp = active

    def step_back(self, context, event):
        """Ctrl-Z (Ctrl-Shift-Z) inside the picker: the last click of this session taken back (put
        again). Blender's own undo steps in only when the picker ends, with the whole session."""
        s = context.scene.headadapt
        source, target = (self.undone, self.done) if event.shift else (self.done, self.undone)
        if source:
            target.append(self.snapshot(s))
            self.restore(s, source.pop())
            self.report({"INFO"}, ("redid" if event.shift else "undid") + " a click")
        self.status(context)
        context.area.tag_redraw()
        return {"RUNNING_MODAL"}

    def finish(self, context):
        context.workspace.status_text_set(None)
        if context.area is not None:            # (Esc pressed after the view's area was closed)
            context.area.tag_redraw()
        return {"FINISHED"}

    def modal(self, context, event):
        s = context.scene.headadapt
        if event.type in {"ESC", "RIGHTMOUSE"} and event.value == "PRESS":
            return self.finish(context)
        if event.type == "Z" and event.value == "PRESS" and (event.ctrl or event.oskey):
            return self.step_back(context, event)
        if event.type in {"MIDDLEMOUSE", "WHEELUPMOUSE", "WHEELDOWNMOUSE"} or event.type.startswith("NDOF"):
            return {"PASS_THROUGH"}
        if event.type in {"LEFTMOUSE", "M"} and not over_view(context.area, event):
            return {"PASS_THROUGH"}                 # the sidebar's FDP list, a header, another editor
        if event.type == "M" and event.value == "PRESS":
            before = self.snapshot(s)
            pts = landmarks.get_landmarks(s.scan)
            guess = landmarks.mirror_suggestion(pts, s.active_fdp)
            if guess is not None:
                pts[s.active_fdp] = guess
                landmarks.set_landmarks(s.scan, pts)
                self.done.append(before)
                self.undone.clear()
                self.report({"INFO"}, f"{s.active_fdp} placed by mirroring {mpeg4.FDPS[s.active_fdp].mirror}")
            context.area.tag_redraw()
            return {"RUNNING_MODAL"}
        if event.type == "LEFTMOUSE" and event.value == "PRESS":
            before = self.snapshot(s)
            origin, direction = mouse_ray(context, event)
            pts = landmarks.get_landmarks(s.scan)
            if event.ctrl:
                size = float(np.ptp(np.array([v[:] for v in s.scan.bound_box]), axis=0).max())
                pts, removed = landmarks.remove_near(s.scan, pts, origin, direction, 0.03 * size)
                if removed:
                    landmarks.set_landmarks(s.scan, pts)
                    self.done.append(before)
                    self.undone.clear()
                    self.report({"INFO"}, f"removed {removed}")
            else:
                pts, ok = landmarks.place(s.scan, pts, s.active_fdp, origin, direction)
                if ok:
                    self.done.append(before)
                    self.undone.clear()
                    landmarks.set_landmarks(s.scan, pts)
                    sug = landmarks.get_landmarks(s.scan, landmarks.SUGGESTED_PROP)
                    if sug.pop(s.active_fdp, None) is not None:      # a moved suggestion is accepted
                        landmarks.set_landmarks(s.scan, sug, prop=landmarks.SUGGESTED_PROP)
                    nxt = landmarks.next_missing(pts, order=landmarks.GUIDED_ORDER, after=s.active_fdp)
                    if nxt:
                        s.active_fdp = nxt
            self.status(context)
            context.area.tag_redraw()
            return {"RUNNING_MODAL"}
        return {"PASS_THROUGH"}


classes = (HEADADAPT_OT_pick_landmarks,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    if not bpy.app.background:
        add_draw_handlers()


def unregister():
    remove_draw_handlers()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

"""The Blender operators and File menu entries of vbusd_blender.

``EXPORT_SCENE_OT_virtual_bones`` (``bpy.ops.export_scene.virtual_bones``) and
``IMPORT_SCENE_OT_virtual_bones`` (``bpy.ops.import_scene.virtual_bones``). Both report a bad
input as one line in Blender's UI (``self.report({'ERROR'}, ...)``) and return ``{'CANCELLED'}``;
the work itself lives in :mod:`vbusd_blender.export` and :mod:`vbusd_blender.importer`.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper


def _names(text: str) -> tuple:
    return tuple(name.strip() for name in text.split(",") if name.strip())


def _user_errors() -> tuple:
    """Exception types reported as one line in the UI: vbusd's errors, and vbusd not installed."""
    try:
        from vbusd import VbusdError
    except ImportError:
        return (ImportError,)
    return (VbusdError, ImportError)


class EXPORT_SCENE_OT_virtual_bones(bpy.types.Operator, ExportHelper):
    """Bake armatures and the meshes they deform into a Virtual Bones animation texture (vbusd)"""

    bl_idname = "export_scene.virtual_bones"
    bl_label = "Export Virtual Bones"
    bl_options = {"REGISTER", "PRESET"}

    filename_ext = ".usda"
    filter_glob: StringProperty(default="*.usda;*.usdc;*.usd", options={"HIDDEN"})

    armatures: StringProperty(
        name="Armatures", default="",
        description="Armature object names, comma separated; empty: the selected armatures (and those of "
                    "selected meshes)")
    source: EnumProperty(
        name="Source", default="ACTIONS",
        items=(("ACTIONS", "Actions", "Each action becomes a clip, evaluated alone (NLA off)"),
               ("TIMELINE", "Timeline", "The scene's frame range as it plays (NLA included): one clip")))
    actions: StringProperty(
        name="Actions", default="",
        description="Action names, comma separated, each a clip; empty: every action that keys a bone of "
                    "the armature (the active one first)")
    encoding: EnumProperty(
        name="Encoding", default="auto",
        items=(("auto", "Auto", "crossMatrix when every bone is rigid, affineMatrix with scale, dualQuat "
                                "for Preserve Volume"),
               ("crossMatrix", "Cross Matrix", "3 texels per bone, rigid (the talk's)"),
               ("affineMatrix", "Affine Matrix", "3 texels per bone, scale and shear allowed"),
               ("quatTranslation", "Quaternion + Translation", "2 texels per bone, uniform scale"),
               ("dualQuat", "Dual Quaternion", "2 texels per bone, rigid, dual-quaternion skinning"),
               ("compactQuatTranslation", "Compact (format 1.2)",
                "1 texel of 12 bytes per bone, rigid; uint32 texels (EXR or KTX2)")))
    texel_format: EnumProperty(
        name="Texel Format", default="float16",
        items=(("float16", "Float 16", "Half floats (EXR)"), ("float32", "Float 32", "Floats (EXR)"),
               ("unorm16", "UNorm 16", "16-bit integers with ranges (PNG)"),
               ("uint32", "UInt 32", "The compact encoding's words (EXR); Float 16 with it means this")))
    container: EnumProperty(
        name="Container", default="auto",
        items=(("auto", "Auto", "EXR for float formats, PNG for unorm16"), ("exr", "OpenEXR", ""),
               ("png", "PNG", "16-bit PNG (unorm16 only)")))
    rows_per_second: FloatProperty(
        name="Rows per Second", default=0.0, min=0.0, max=10000.0,
        description="Texture rows per second of every clip; 0 keeps the scene's frame rate")
    horizontal_padding: EnumProperty(
        name="Horizontal Padding", default="powerOfTwo",
        items=(("powerOfTwo", "Power of Two", ""), ("none", "None", "")))
    vertical_padding: EnumProperty(
        name="Vertical Padding", default="none",
        items=(("none", "None", ""), ("powerOfTwo", "Power of Two", "Resample clips to fill a power of two")))
    max_influences: IntProperty(name="Max Influences", default=4, min=1, max=64,
                                description="Bone influences kept per vertex (the largest, renormalized)")
    loop: EnumProperty(
        name="Loop", default="AUTO",
        items=(("AUTO", "Auto", "An action's Cyclic Animation flag (manual frame range), else loop when the "
                                "first and last poses agree"),
               ("ON", "Loop", "Every clip loops"), ("OFF", "Clamp", "Every clip holds its ends")))
    overwrite: BoolProperty(name="Overwrite", default=True,
                            description="Replace an existing layer, texture and sidecar")
    reset_pose: BoolProperty(name="Reset Pose Between Actions", default=True,
                             description="Before each action, put pose bones at rest so channels it does not "
                                         "key do not keep what the previous action left")

    def execute(self, context):
        from .export import ExportSettings, export_virtual_bones

        settings = ExportSettings(
            armatures=_names(self.armatures), actions=_names(self.actions), source=self.source,
            encoding=self.encoding, texel_format=self.texel_format, container=self.container,
            rows_per_second=self.rows_per_second, horizontal_padding=self.horizontal_padding,
            vertical_padding=self.vertical_padding, max_influences=self.max_influences, loop=self.loop,
            overwrite=self.overwrite, reset_pose=self.reset_pose)
        wm = context.window_manager
        started = []

        def progress(done, total):
            if not started:
                wm.progress_begin(0, max(1, total))
                started.append(True)
            wm.progress_update(done)

        try:
            report = export_virtual_bones(context, self.filepath, settings, progress)
        except _user_errors() as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        finally:
            if started:
                wm.progress_end()
        for warning in report.warnings:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, report.summary())
        return {"FINISHED"}


class IMPORT_SCENE_OT_virtual_bones(bpy.types.Operator, ImportHelper):
    """Import a Virtual Bones asset (vbusd USD layer): rest meshes, an armature per animation, crowds"""

    bl_idname = "import_scene.virtual_bones"
    bl_label = "Import Virtual Bones"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ".usda"
    filter_glob: StringProperty(default="*.usda;*.usdc;*.usd", options={"HIDDEN"})

    crowds: BoolProperty(name="Crowds", default=True,
                         description="Import point-instanced crowds, one rig per instance")
    max_instances: IntProperty(name="Max Instances", default=2000, min=0,
                               description="Import at most this many instances per crowd")
    keys_per_row: IntProperty(
        name="Keys per Row", default=4, min=1, max=64,
        description="Keyframes per texture row; more follow the texture's own interpolation between rows "
                    "more closely")
    allow_outside_paths: BoolProperty(
        name="Allow Outside Paths", default=False,
        description="Let the asset reference files outside its folder")

    def execute(self, context):
        from .importer import ImportSettings, import_virtual_bones

        settings = ImportSettings(crowds=self.crowds, max_instances=self.max_instances,
                                  keys_per_row=self.keys_per_row, allow_outside_paths=self.allow_outside_paths)
        try:
            report = import_virtual_bones(context, self.filepath, settings)
        except _user_errors() as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        for warning in report.warnings:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, report.summary())
        return {"FINISHED"}


def menu_export(self, context):
    """File > Export > Virtual Bones."""
    self.layout.operator(EXPORT_SCENE_OT_virtual_bones.bl_idname, text="Virtual Bones (.usda)")


def menu_import(self, context):
    """File > Import > Virtual Bones."""
    self.layout.operator(IMPORT_SCENE_OT_virtual_bones.bl_idname, text="Virtual Bones (.usda)")


CLASSES = (EXPORT_SCENE_OT_virtual_bones, IMPORT_SCENE_OT_virtual_bones)

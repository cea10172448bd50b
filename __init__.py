# Blender loads the extension from the repository root (blender_manifest.toml lives here);
# the add-on itself is the headadapt_addon package. Guarded so pytest can collect the tree.
if __package__:
    from .headadapt_addon import register, unregister  # noqa: F401

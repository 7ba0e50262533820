"""Scene files: the TOML format's keys, validation, --set overrides, the build of a System and its
Structure, ``load_scene`` and ``Scene.run``, and the [expect] checks of a finished run."""

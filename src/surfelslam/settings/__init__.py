"""Settings machinery, in one place: typed fields with units, bounds and a tier (:mod:`.fields`), TOML files
(:mod:`.tomlio`), ``--set`` overrides (:mod:`.overrides`), packaged presets (:mod:`.presets`) and the generated
reference page (:mod:`.reference`). The bottom layer: it imports nothing of the project but ``errors``."""

from surfelslam.settings.fields import (
    Bounds,
    Config,
    check,
    check_rules,
    field_bounds,
    field_types,
    fmt_value,
    is_user_setting,
    iter_tables,
    join_path,
    ordered,
    setting,
    validate,
)
from surfelslam.settings.overrides import apply_sets, load_config, parse_set
from surfelslam.settings.presets import preset_names, presets_dir, resolve_config_path
from surfelslam.settings.tomlio import (
    VERSION_KEY,
    dumps_toml,
    from_dict,
    load_toml,
    package_version,
    to_dict,
    toml_value,
)

__all__ = [
    "VERSION_KEY", "Bounds", "Config", "apply_sets", "check", "check_rules", "dumps_toml", "field_bounds",
    "field_types", "fmt_value", "from_dict", "is_user_setting", "iter_tables", "join_path", "load_config",
    "load_toml", "ordered", "package_version", "parse_set", "preset_names", "presets_dir", "resolve_config_path",
    "setting", "to_dict", "toml_value", "validate",
]

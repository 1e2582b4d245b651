"""backend stage of papl-mapper: global and local bundle adjustment in gtsam (the only gtsam importer).

`global_ba(map, config, progress) -> BAResult` and `local_ba(map, keyframe_ids, config, progress)`;
the result carries an optimised copy of the Map and the statistics.
"""

from papl_mapper.backend.ba import BAResult, global_ba, local_ba
from papl_mapper.backend.config import BAConfig

__all__ = ["BAConfig", "BAResult", "global_ba", "local_ba"]

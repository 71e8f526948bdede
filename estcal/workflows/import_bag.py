"""``estcal import-bag``: one dataset row per static plateau of a ROS 1 or ROS 2 bag (:mod:`estcal.io.bags`)."""
from __future__ import annotations

__all__ = ["import_bag_file"]


def import_bag_file(bag, output, joints_topic: str, pose_topic=None, point_topics=(), **options):
    """Import ``bag`` and write the rows to ``output`` (CSV); returns the :class:`~estcal.io.bags.BagImport`."""
    from estcal.io.bags import BagError, import_bag

    out = import_bag(bag, joints_topic, pose_topic, tuple(point_topics or ()), **options)
    if out.n == 0:
        raise BagError(f"{bag}: no plateau has measurements in its window ({len(out.skipped)} skipped)")
    out.write_csv(output)
    return out

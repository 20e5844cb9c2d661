"""The OSM reader against the real extracts in ../shared/data/osm (ODbL) and small hand-written ones.

Counts, heights and positions are checked against the files themselves, read independently with a
plain pyosmium handler (no area assembly, no reader code).
"""

import logging
import re
import shutil

import numpy as np
import osmium
import pymap3d
import pytest
import shapely
import yaml

from conftest import SHARED_DATA
from simart_pipeline.config import ConfigError, Materials, load_scene_config
from simart_pipeline.scene import geometry, source
from simart_pipeline.scene.osm import OsmReadError, read_extract
from simart_pipeline.scene.osm_tags import building_heights, parse_length_m, roof_of

OSM = SHARED_DATA / "osm"
EXTRACTS = ["small_block.osm", "neukolln.osm", "taipei.osm", "helsinki.osm.pbf"]


@pytest.mark.parametrize("text,metres", [("12", 12.0), ("12 m", 12.0), ("12.5m", 12.5), ("40'", 12.192),
                                         ("40 ft", 12.192), ("3,5", 3.5), ("12'6\"", 3.81), ("~7 m", 7.0),
                                         ("tall", None), ("12;15", None), (None, None)])
def test_parse_length(text, metres):
    assert parse_length_m(text) == (pytest.approx(metres) if metres is not None else None)


def test_height_rules():
    assert building_heights({"height": "21 m"}, 10, 3) == (0.0, 21.0)
    assert building_heights({"height": "40'", "min_height": "10 ft"}, 10, 3) == pytest.approx((3.048, 12.192))
    assert building_heights({"building:levels": "4", "roof:levels": "1"}, 10, 3) == (0.0, 15.0)
    assert building_heights({"building:levels": "4", "roof:height": "2.5"}, 10, 3) == (0.0, 14.5)
    assert building_heights({"building:levels": "4", "building:min_level": "1"}, 10, 3) == (3.0, 12.0)
    assert building_heights({"height": "-3"}, 10, 3) == (0.0, 10.0)          # nonsense: the default
    assert building_heights({"height": "9", "min_height": "12"}, 10, 3) == (0.0, 9.0)
    assert building_heights({}, 10, 3) == (0.0, 10.0)


def test_roof_rules():
    assert roof_of({}, 10, 0, 3) == ("flat", 0.0, False)
    assert roof_of({"roof:shape": "gabled", "roof:height": "4 m"}, 10, 0, 3) == ("gabled", 4.0, False)
    assert roof_of({"roof:shape": "hipped", "roof:levels": "1"}, 10, 0, 3) == ("hipped", 3.0, False)
    shape, rise, across = roof_of({"roof:shape": "gambrel", "roof:orientation": "across"}, 10, 0, 3)
    assert shape == "gabled" and np.isnan(rise) and across      # approximated; height from the pitch
    assert roof_of({"roof:shape": "gabled", "roof:height": "30"}, 10, 2, 3)[1] == 8.0  # at most the span
    assert roof_of({"roof:shape": "weird"}, 10, 0, 3)[0] == "flat"


class _Buildings(osmium.SimpleHandler):
    """Every object tagged building=* in a file: complete closed ways (with their first node's
    position and their tags) and multipolygon relations."""

    def __init__(self):
        super().__init__()
        self.ways, self.incomplete_ways, self.relations = {}, set(), set()

    def way(self, w):
        if w.tags.get("building", "no") == "no" or w.tags.get("location") == "underground":
            return
        nodes = list(w.nodes)
        if len(nodes) >= 4 and nodes[0].ref == nodes[-1].ref and all(n.location.valid() for n in nodes):
            self.ways[w.id] = (nodes[0].lat, nodes[0].lon, dict(w.tags))
        else:
            self.incomplete_ways.add(w.id)

    def relation(self, r):
        if r.tags.get("building", "no") != "no" and r.tags.get("type") == "multipolygon":
            self.relations.add(r.id)


@pytest.fixture(scope="module")
def extracts():
    out = {}
    for name in EXTRACTS:
        path = OSM / name
        assert path.is_file(), f"shared test data missing: {path}"
        h = _Buildings()
        h.apply_file(str(path), locations=True)
        out[name] = (h, read_extract(path))
    return out


@pytest.mark.parametrize("name", EXTRACTS)
def test_every_building_of_the_file_is_built_or_named_in_a_warning(extracts, name):
    h, geom = extracts[name]
    built = {f.source_id for f in geom.of_class("building")}
    assert {i for i in built if i > 0} == set(h.ways)          # every complete closed way, no other
    rel_built = {-i for i in built if i < 0}
    assert rel_built <= h.relations
    for oid, kind in [(i, "way") for i in h.incomplete_ways] + [(i, "relation") for i in h.relations - rel_built]:
        assert any(f"building {kind} {oid}:" in w and "dropped" in w for w in geom.warnings), (kind, oid)
    assert len(built) == len(h.ways) + len(rel_built) > 20


@pytest.mark.parametrize("name", EXTRACTS)
def test_heights_and_positions_match_the_tags_and_the_projection(extracts, name):
    h, geom = extracts[name]
    lat0, lon0, alt0 = geom.origin
    checked = 0
    for f in geom.of_class("building"):
        if f.source_id not in h.ways:
            continue
        lat, lon, tags = h.ways[f.source_id]
        if re.fullmatch(r"\d+(\.\d+)?", tags.get("height", "")):
            assert f.height_m == float(tags["height"])
        elif "height" not in tags and re.fullmatch(r"\d+", tags.get("building:levels", "")) \
                and not {"roof:levels", "roof:height"} & set(tags):
            assert f.height_m == 3.0 * int(tags["building:levels"])
        elif not {"height", "building:levels", "min_height", "building:min_level"} & set(tags):
            assert f.height_m == 10.0
        if re.fullmatch(r"\d+(\.\d+)?", tags.get("min_height", "")):
            assert f.min_height_m == float(tags["min_height"])
        e, n, _ = pymap3d.geodetic2enu(lat, lon, alt0, lat0, lon0, alt0)
        ring = np.concatenate([p.exterior.coords for p in geometry.polygons_of(f.geometry)])
        assert np.min(np.hypot(ring[:, 0] - e, ring[:, 1] - n)) < 1e-6
        checked += 1
    assert checked > 20


def test_origin_defaults_to_the_extract_centre(extracts):
    _, geom = extracts["helsinki.osm.pbf"]
    reader = osmium.io.Reader(str(OSM / "helsinki.osm.pbf"), osmium.osm.osm_entity_bits.NOTHING)
    box = reader.header().box()
    reader.close()
    assert geom.origin[:2] == pytest.approx(((box.bottom_left.lat + box.top_right.lat) / 2,
                                             (box.bottom_left.lon + box.top_right.lon) / 2), abs=1e-12)
    ground = geom.of_class("ground")[0].geometry
    assert ground.centroid.distance(shapely.Point(0, 0)) < 5.0 + 0.1 * np.sqrt(ground.area)


def _enu_box(lon_lat: np.ndarray, origin) -> shapely.Polygon:
    e, n, _ = pymap3d.geodetic2enu(lon_lat[:, 1], lon_lat[:, 0], 0.0, origin[0], origin[1], 0.0)
    return shapely.box(e.min(), n.min(), e.max(), n.max())


def test_an_extract_without_a_header_box_spans_its_nodes(tmp_path):
    # One small building in the south-west corner, a road 400 m away to the north-east and a lone node
    # beyond it: no <bounds>, as Overpass writes them. The buildings' box would drop the road.
    nodes = {1: (11.0000, 48.0000), 2: (11.0002, 48.0000), 3: (11.0002, 48.0002), 4: (11.0000, 48.0002),
             5: (11.0040, 48.0030), 6: (11.0050, 48.0030), 7: (11.0060, 48.0045)}
    xml = ['<?xml version="1.0" encoding="UTF-8"?>', '<osm version="0.6" generator="Overpass API">']
    xml += [f'<node id="{i}" lat="{lat}" lon="{lon}" version="1"/>' for i, (lon, lat) in nodes.items()]
    xml += ['<way id="10" version="1"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="4"/><nd ref="1"/>'
            '<tag k="building" v="yes"/></way>',
            '<way id="11" version="1"><nd ref="5"/><nd ref="6"/><tag k="highway" v="residential"/></way>', '</osm>']
    path = tmp_path / "overpass.osm"
    path.write_text("\n".join(xml))
    geom = read_extract(path)
    ll = np.array(list(nodes.values()))
    assert geom.origin[:2] == pytest.approx(((ll[:, 1].min() + ll[:, 1].max()) / 2,
                                             (ll[:, 0].min() + ll[:, 0].max()) / 2), abs=1e-12)
    (ground,) = geom.of_class("ground")
    # the nodes' box in the local frame (its edges are parallels and meridians: curved by mm)
    assert ground.geometry.buffer(0.01).covers(_enu_box(ll, geom.origin))
    assert ground.geometry.area == pytest.approx(_enu_box(ll, geom.origin).area, rel=1e-4)
    (road,) = geom.of_class("road")
    e, n, _ = pymap3d.geodetic2enu(ll[4:6, 1], ll[4:6, 0], 0.0, geom.origin[0], geom.origin[1], 0.0)
    assert road.geometry.length == pytest.approx(np.hypot(*np.diff([e, n], axis=1)[:, 0]), rel=1e-9)  # whole


def test_taipei_ground_holds_every_node_of_the_extract(extracts):
    # taipei.osm (Overpass, no header box): its 61 buildings cover a third of the area its roads do
    _, geom = extracts["taipei.osm"]
    ll = np.array([(n.location.lon, n.location.lat) for n in osmium.FileProcessor(str(OSM / "taipei.osm"), osmium.osm.NODE)
                   if n.location.valid()])
    (ground,) = geom.of_class("ground")
    assert ground.geometry.buffer(0.01).covers(_enu_box(ll, geom.origin))
    bld = shapely.bounds([f.geometry for f in geom.of_class("building")])
    assert shapely.box(*bld[:, :2].min(0), *bld[:, 2:].max(0)).area < 0.5 * ground.geometry.area


def test_bbox_clips_roads_and_keeps_whole_buildings_inside():
    bbox = (24.940, 60.166, 24.948, 60.172)
    geom = read_extract(OSM / "helsinki.osm.pbf", bbox_deg=bbox)
    lat0, lon0, _ = geom.origin
    assert (lat0, lon0) == pytest.approx(((bbox[1] + bbox[3]) / 2, (bbox[0] + bbox[2]) / 2))
    corners = np.array([pymap3d.geodetic2enu(la, lo, 0, lat0, lon0, 0)[:2]
                        for lo, la in [(bbox[0], bbox[1]), (bbox[2], bbox[1]), (bbox[2], bbox[3]), (bbox[0], bbox[3])]])
    box = shapely.Polygon(corners).buffer(0.05)  # the box's edges are parallels: curved in ENU, by mm
    whole = read_extract(OSM / "helsinki.osm.pbf", origin=geom.origin)
    inside = {f.source_id for f in whole.of_class("building") if box.contains(f.geometry.representative_point())}
    assert {f.source_id for f in geom.of_class("building")} == inside and 10 < len(inside) < 446
    for f in geom.features:
        if f.feature_class in ("road", "parking", "water", "vegetation", "ground"):
            assert box.contains(f.geometry), f.source_id
    kept = {f.source_id: f for f in geom.of_class("building")}
    for f in whole.of_class("building"):   # buildings are kept whole, not cut
        if f.source_id in kept:
            assert kept[f.source_id].geometry.equals_exact(f.geometry, 1e-9)


URBAN = """<?xml version='1.0' encoding='UTF-8'?>
<osm version="0.6">
  <node id="1" lat="48.00000" lon="11.00000"/><node id="2" lat="48.00000" lon="11.00040"/>
  <node id="3" lat="48.00030" lon="11.00040"/><node id="4" lat="48.00030" lon="11.00000"/>
  <node id="5" lat="48.00010" lon="11.00010"/><node id="6" lat="48.00010" lon="11.00020"/>
  <node id="7" lat="48.00020" lon="11.00020"/><node id="8" lat="48.00020" lon="11.00010"/>
  <node id="11" lat="48.00100" lon="11.00000"/><node id="12" lat="48.00100" lon="11.00030"/>
  <node id="13" lat="48.00120" lon="11.00000"/><node id="14" lat="48.00120" lon="11.00030"/>
  <node id="21" lat="47.99990" lon="10.99990"/><node id="22" lat="47.99990" lon="11.00050"/>
  <way id="100"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="4"/><nd ref="1"/>
    <tag k="building" v="yes"/><tag k="height" v="20"/></way>
  <way id="101"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="4"/><nd ref="1"/>
    <tag k="building:part" v="yes"/><tag k="height" v="10"/><tag k="building:material" v="brick"/></way>
  <way id="102"><nd ref="5"/><nd ref="6"/><nd ref="7"/><nd ref="8"/><nd ref="5"/>
    <tag k="building:part" v="yes"/><tag k="min_height" v="10"/><tag k="height" v="30"/>
    <tag k="roof:shape" v="pyramidal"/><tag k="roof:height" v="4"/></way>
  <way id="110"><nd ref="11"/><nd ref="14"/><nd ref="12"/><nd ref="13"/><nd ref="11"/>
    <tag k="building" v="yes"/><tag k="building:levels" v="3"/></way>
  <way id="120"><nd ref="21"/><nd ref="22"/><tag k="highway" v="residential"/><tag k="lanes" v="2"/>
    <tag k="surface" v="sett"/></way>
</osm>
"""


def test_building_parts_bow_tie_repair_roads_and_materials(tmp_path, caplog):
    path = tmp_path / "parts.osm"
    path.write_text(URBAN)
    with caplog.at_level(logging.WARNING):
        geom = read_extract(path, origin=(48.0, 11.0, 0.0), materials=Materials(tags={"surface": {"sett": "brick"}}))
    outline = {f.source_id: f for f in geom.of_class("building")}
    parts = {f.source_id: f for f in geom.of_class("building_part")}
    # Simple 3D Buildings: the outline with parts is not a volume, its parts are, labelled with its id
    assert outline[100].has_parts and {p.parent_id for p in parts.values()} == {100}
    assert {f.source_id for f in geom.volumes()} == {101, 102, 110}
    assert (parts[102].min_height_m, parts[102].height_m, parts[102].roof_shape) == (10.0, 30.0, "pyramidal")
    assert parts[101].radio_material == "brick" and outline[100].radio_material == "concrete"
    # the bow-tie way 110 is repaired into its two triangles, with a warning naming it
    bow = outline[110]
    assert isinstance(bow.geometry, shapely.MultiPolygon) and len(bow.geometry.geoms) == 2
    assert bow.height_m == 9.0 and bow.geometry.is_valid
    assert any("building way 110" in r.getMessage() and "repaired" in r.getMessage() for r in caplog.records)
    assert any("building way 110" in w for w in geom.warnings)
    (road,) = geom.of_class("road")
    assert road.width_m == 7.0 and road.radio_material == "brick"  # 2 lanes x 3.5 m; user's tag rule
    # CF ragged arrays round-trip everything, multipolygons and holes included
    back = geometry.from_dataset(geometry.to_dataset(geom))
    for a, b in zip(back.features, geom.features):
        assert a.geometry.equals_exact(b.geometry, 0) and a.parent_id == b.parent_id
        assert (a.has_parts, a.roof_shape, a.radio_material) == (b.has_parts, b.roof_shape, b.radio_material)
    assert back.origin == geom.origin and back.warnings == geom.warnings


def test_helsinki_round_trips_through_the_dataset(extracts):
    _, geom = extracts["helsinki.osm.pbf"]
    ds = geometry.to_dataset(geom)
    assert ds.sizes["part"] > ds.sizes["feature"]           # holes and multipolygons are kept
    back = geometry.from_dataset(ds)
    assert len(back.features) == len(geom.features)
    for a, b in zip(back.features, geom.features):
        assert a.geometry.equals_exact(b.geometry, 0) and a.source_id == b.source_id
        assert a.height_m == b.height_m or (np.isnan(a.height_m) and np.isnan(b.height_m))


BAD_INPUTS = {
    "malformed.osm": "<osm version='0.6'><node id='1' lat='48.1' lon='10.0'><tag k='a'",
    "external_entity.osm": ('<?xml version="1.0"?><!DOCTYPE osm [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>'
                            '<osm version="0.6"><node id="1" lat="1" lon="1"><tag k="building" v="&xxe;"/></node></osm>'),
    "billion_laughs.osm": ('<?xml version="1.0"?><!DOCTYPE osm [<!ENTITY a "aaaaaaaaaa">'
                           '<!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;"><!ENTITY c "&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;">]>'
                           '<osm version="0.6"><node id="1" lat="1" lon="1"><tag k="n" v="&c;"/></node></osm>'),
    "empty.osm": '<?xml version="1.0"?><osm version="0.6"></osm>',
    "zero_bytes.osm": "",
    "no_buildings.osm": ('<osm version="0.6"><node id="1" lat="48" lon="11"/><node id="2" lat="48.001" lon="11"/>'
                         '<way id="3"><nd ref="1"/><nd ref="2"/><tag k="highway" v="residential"/></way></osm>'),
    "not_osm.osm.pbf": "this is not a protocol buffer",
}
BAD_MESSAGES = {"malformed.osm": "XML parsing error", "external_entity.osm": "entities are not supported",
                "billion_laughs.osm": "entities are not supported", "empty.osm": "empty",
                "zero_bytes.osm": "not a readable OSM file", "no_buildings.osm": "no building",
                "not_osm.osm.pbf": "not a readable OSM file"}


@pytest.mark.parametrize("name", sorted(BAD_INPUTS))
def test_bad_extracts_are_refused_naming_the_file(tmp_path, name):
    path = tmp_path / name
    path.write_text(BAD_INPUTS[name])
    with pytest.raises(OsmReadError) as err:
        read_extract(path)
    assert str(path) in str(err.value) and BAD_MESSAGES[name] in str(err.value)


def _osm_scene(tmp_path, source_path: str):
    d = tmp_path / "osm_scene"
    d.mkdir(exist_ok=True)
    (d / "scene.yaml").write_text(yaml.safe_dump({
        "name": "osm_scene", "source": {"kind": "osm", "path": source_path},
        "origin": {"latitude_deg": 48.136, "longitude_deg": 10.069, "altitude_m": 0.0},
        "base_stations": [{"name": "bs0", "position_m": [0, 0, 50]}],
        "platforms": [{"name": "p0", "kind": "pedestrian",
                       "trajectory": {"waypoints_m": [[0, 0, 60], [1, 0, 60]], "speed_mps": 1}}],
        "clock": {"duration_s": 1}}))
    return d


def test_scene_config_reads_an_extract_inside_its_folder(tmp_path):
    d = _osm_scene(tmp_path, "extract.osm")
    shutil.copyfile(OSM / "small_block.osm", d / "extract.osm")
    cfg = load_scene_config(d)
    geom = source.build_source_geometry(cfg, d)
    assert geom.origin == (48.136, 10.069, 0.0) and len(geom.of_class("building")) > 20


def test_a_symlink_leading_out_of_the_scene_folder_is_refused(tmp_path):
    d = _osm_scene(tmp_path, "extract.osm")
    (d / "extract.osm").symlink_to(OSM / "small_block.osm")  # the same rule as recordings and bags
    with pytest.raises(ConfigError, match=r"source\.path: 'extract\.osm' points outside the scene directory"):
        load_scene_config(d)


@pytest.mark.parametrize("bad", ["../outside.osm", "/etc/passwd", "sub/../../x.osm"])
def test_scene_config_paths_outside_the_scene_folder_are_refused(tmp_path, bad):
    d = _osm_scene(tmp_path, bad)
    with pytest.raises(ConfigError) as err:
        load_scene_config(d)
    assert f"{d / 'scene.yaml'}: source.path" in str(err.value) and "inside the scene directory" in str(err.value)

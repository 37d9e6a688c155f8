"""Photos without cameras posed by COLMAP through pycolmap (``usplat pose``), into a folder the
other commands read as it is.

The steps are COLMAP's own (https://colmap.github.io/tutorial.html): SIFT features, matching
(every pair, or each photo with its neighbours in name order for video frames) with
geometric verification, incremental mapping, then ``image_undistorter``: the model and the
photos resampled to a distortion-free ``PINHOLE`` camera, which the model (a pinhole) needs.
The result is COLMAP's dense workspace layout::

    OUT/images/        the photos, undistorted (file names kept)
    OUT/sparse/        cameras.bin, images.bin, points3D.bin (PINHOLE): --cameras OUT/sparse
    OUT/distorted/     database.db and sparse/0, the model before undistortion
    OUT/pose.json      what was asked and what registered

``usplat import --colmap OUT`` finds ``OUT/sparse`` and ``OUT/images``; ``usplat render
--cameras OUT/sparse --images OUT/images/a.jpg OUT/images/b.jpg`` and ``usplat view`` read
them the same way. One shared camera is solved when the photos' EXIF names one camera
(make, model, focal length) and one size, or when none names a camera and all share a size
(video frames, renders); otherwise one camera per photo (internet photos).

The scale of the world is COLMAP's, arbitrary: scene units mean nothing in metres, and
near/far come from the sparse points.
"""

import hashlib
import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from usplat_dr.io import write_json
from usplat_dr.io.user_files import open_image, read_bytes, read_image, regular_file, sha256

log = logging.getLogger(__name__)

#: ``matching="auto"``: every pair up to this many photos, then neighbours in name order.
EXHAUSTIVE_UP_TO = 100
#: Photos one call may pose (exhaustive matching grows with the square of the count).
MAX_PHOTOS = 2000
#: Bytes one photo may hold (the bound of ``io.user_files`` for images).
MAX_PHOTO_BYTES = 256 * 2**20
#: EXIF tags that name a camera: Make, Model (IFD0) and FocalLength (the Exif IFD).
EXIF_MAKE, EXIF_MODEL, EXIF_IFD, EXIF_FOCAL = 0x010F, 0x0110, 0x8769, 0x920A


@dataclass(frozen=True)
class PoseSettings:
    """How ``pose_photos`` runs COLMAP.

    ``matching``: ``"exhaustive"`` (every pair), ``"sequential"`` (each photo with its
    ``overlap`` neighbours in name order: video frames) or ``"auto"`` (exhaustive up to
    ``EXHAUSTIVE_UP_TO`` photos). ``camera``: ``"single"`` (one camera for all),
    ``"per-image"`` or ``"auto"`` (``one_camera``). ``max_image_size``:
    the long side SIFT sees (COLMAP's default is 3200; 1600 keeps phone photos fast).
    ``seed``: COLMAP's random seed (RANSAC, mapping). ``threads``: -1 for every core."""

    matching: str = "auto"
    camera: str = "auto"
    max_image_size: int = 1600
    overlap: int = 10
    seed: int = 0
    threads: int = -1

    def __post_init__(self):
        if self.matching not in ("auto", "exhaustive", "sequential"):
            raise ValueError(f"matching must be 'auto', 'exhaustive' or 'sequential', got "
                             f"{self.matching!r}")
        if self.camera not in ("auto", "single", "per-image"):
            raise ValueError(f"camera must be 'auto', 'single' or 'per-image', got "
                             f"{self.camera!r}")
        if self.max_image_size < 64:
            raise ValueError(f"max_image_size must be >= 64 pixels, got {self.max_image_size}")
        if self.overlap < 1:
            raise ValueError(f"overlap must be >= 1, got {self.overlap}")


@dataclass
class PoseResult:
    """What ``pose_photos`` wrote: the COLMAP model folder (``model``: PINHOLE), the
    undistorted photos' folder, the names registered and not, the mean reprojection error
    (pixels, before undistortion) and the number of sparse points."""

    model: Path
    images: Path
    registered: list[str]
    unregistered: list[str]
    mean_reprojection_error: float
    points: int
    camera_mode: str
    matching: str
    seconds: float

    def line(self) -> str:
        total = len(self.registered) + len(self.unregistered)
        return (f"registered {len(self.registered)} of {total} photos "
                f"({self.points:,} points, mean reprojection error "
                f"{self.mean_reprojection_error:.2f} px, {self.camera_mode} camera, "
                f"{self.matching} matching, {self.seconds:.0f} s): --cameras {self.model}")


def _pycolmap():
    try:  # an optional extra (usplat-dr[pose]): imported where posing is asked for
        import pycolmap
    except ImportError:
        raise ValueError("posing photos needs pycolmap (COLMAP's Python bindings): pip install "
                         "'usplat-dr[pose]' (or pip install pycolmap), or pose them with "
                         "COLMAP yourself and pass --cameras") from None
    return pycolmap


def exif_camera(path: Path) -> tuple:
    """(make, model, focal length, width, height) of a photo from its EXIF and header;
    missing tags are None."""
    im = open_image(read_bytes(path, "photo", MAX_PHOTO_BYTES), f"photo {path}")
    exif = im.getexif()
    focal = exif.get_ifd(EXIF_IFD).get(EXIF_FOCAL)
    return (exif.get(EXIF_MAKE), exif.get(EXIF_MODEL),
            None if focal is None else float(focal), *im.size)


def one_camera(paths: list[Path]) -> bool:
    """Whether the photos were taken by one camera: the same EXIF make, model and focal
    length and the same size, or, none of them carrying a make or model (frames of a video,
    renders, screenshots), the same size. Photos of several cameras (internet photos) carry
    their EXIF or differ in size."""
    seen = {exif_camera(p) for p in paths}
    if len(seen) == 1:
        return True
    return (all(make is None and model is None for make, model, *_ in seen)
            and len({(w, h) for *_, w, h in seen}) == 1)


def gather_photos(photos: list[Path], folder: Path) -> list[str]:
    """Hard-link (or copy) ``photos`` into ``folder`` under their own names; the names.
    Two photos of one name (from two folders) are an error naming both."""
    by_name: dict[str, Path] = {}
    for p in photos:
        regular_file(p, "photo", MAX_PHOTO_BYTES)
        if p.name in by_name and by_name[p.name].resolve() != p.resolve():
            raise ValueError(f"two photos are named {p.name!r} ({by_name[p.name]} and {p}): "
                             "COLMAP names images by file name; rename one")
        by_name[p.name] = p
        read_image(p, "photo")  # PNG or JPEG, its size bounded: refused here, not by COLMAP
    folder.mkdir(parents=True, exist_ok=True)
    for name, p in by_name.items():
        dst = folder / name
        if dst.exists():
            dst.unlink()
        try:
            os.link(p, dst)
        except OSError:  # another file system, or links not allowed
            shutil.copyfile(p, dst)
    return sorted(by_name)


def photos_in(folder: Path) -> list[Path]:
    """The PNG and JPEG files of ``folder`` (not its subfolders), by name."""
    if not folder.is_dir():
        raise FileNotFoundError(f"--images {folder} is not a folder of photos")
    out = sorted(p for p in folder.iterdir()
                 if p.is_file() and p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if not out:
        raise ValueError(f"--images {folder} holds no .jpg, .jpeg or .png file")
    return out


def why_unregistered(database: Path, names: list[str], registered: set[str]) -> list[str]:
    """One reason per photo that did not register: its features and the verified matches
    it has with any other photo."""
    pycolmap = _pycolmap()
    db = pycolmap.Database.open(str(database))
    try:
        ids = {img.name: img.image_id for img in db.read_all_images()}
        partners: dict[int, list[int]] = {i: [] for i in ids.values()}
        pair_ids, geometries = db.read_two_view_geometries()
        for pair, geometry in zip(pair_ids, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pair)
            n = len(geometry.inlier_matches)
            partners.setdefault(a, []).append(n)
            partners.setdefault(b, []).append(n)
        out = []
        for name in names:
            if name in registered:
                continue
            if name not in ids:
                out.append(f"{name}: not read by COLMAP")
                continue
            i = ids[name]
            best = max(partners.get(i, []), default=0)
            out.append(f"{name}: {db.num_keypoints_for_image(i):,} features, at most "
                       f"{best} verified matches with another photo")
        return out
    finally:
        db.close()


def mapping_options(pycolmap, settings: PoseSettings, photos: int, two_view_tracks: bool,
                    init_min_tri_angle: float):
    """COLMAP's incremental mapping options for ``photos`` photos: its defaults, with the
    seed and threads of ``settings``, a model of two photos allowed, and the two settings
    ``pose_photos`` relaxes on its second attempt."""
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = settings.threads
    mapping.random_seed = settings.seed
    mapping.min_model_size = min(mapping.min_model_size, photos)
    mapping.mapper.init_min_tri_angle = init_min_tri_angle
    mapping.triangulation.ignore_two_view_tracks = not two_view_tracks
    return mapping


def pose_photos(photos: list[str | os.PathLike], out: str | os.PathLike,
                settings: PoseSettings = PoseSettings(), progress: bool = True) -> PoseResult:
    """Pose ``photos`` (at least 2 PNG or JPEG files) with COLMAP into ``out`` (module
    docstring). A ``ValueError`` when fewer than two register, naming each photo that did
    not and why (its features and verified matches)."""
    pycolmap = _pycolmap()
    t0 = time.perf_counter()
    paths = [Path(p) for p in photos]
    if len(paths) < 2:
        raise ValueError(f"posing needs at least 2 photos, got {len(paths)}")
    if len(paths) > MAX_PHOTOS:
        raise ValueError(f"{len(paths):,} photos: at most {MAX_PHOTOS:,} in one call (pose a "
                         "subset, or run COLMAP itself on large captures)")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file: pass a folder")
    work = out / "distorted"
    if work.exists():  # a rerun starts afresh (an earlier, killed one's database included)
        shutil.rmtree(work)
    raw_images = work / "photos"
    names = gather_photos(paths, raw_images)
    mode = settings.camera
    if mode == "auto":
        mode = "single" if one_camera([raw_images / n for n in names]) else "per-image"
    matching = settings.matching
    if matching == "auto":
        matching = "exhaustive" if len(names) <= EXHAUSTIVE_UP_TO else "sequential"
    # COLMAP's own log (hundreds of lines) only for its warnings; the steps are logged here
    pycolmap.logging.minloglevel = pycolmap.logging.Level.WARNING.value
    pycolmap.set_random_seed(settings.seed)
    database = work / "database.db"

    say = log.info
    say("pose: %d photos, %s camera, %s matching (pycolmap %s)", len(names), mode, matching,
        getattr(pycolmap, "__version__", "?"))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = settings.threads
    extraction.max_image_size = settings.max_image_size
    camera_mode = {"single": pycolmap.CameraMode.SINGLE,
                   "per-image": pycolmap.CameraMode.PER_IMAGE}[mode]
    say("pose: extracting features")
    pycolmap.extract_features(database, raw_images, image_names=names, camera_mode=camera_mode,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matcher = pycolmap.FeatureMatchingOptions()
    matcher.num_threads = settings.threads
    say("pose: matching (%s)", matching)
    if matching == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matcher,
                                  device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = settings.overlap
        pycolmap.match_sequential(database, matching_options=matcher, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    counter = {"n": 0}

    def registered_one():
        counter["n"] += 1
        if progress:
            say("pose: mapping, %d of %d photos registered", counter["n"], len(names))

    sparse_raw = work / "sparse"
    best = None
    # COLMAP's defaults first; then, where they make no model of two or more photos, tracks
    # seen by two photos only kept as points and a smaller initial triangulation angle: with
    # two or three photos nearly every track is a two-view one, which the defaults drop (two
    # neighbouring phone photos with 1,378 verified matches made no model without this)
    for attempt in ((False, 16.0), (True, 8.0)):
        if len(names) <= 3 and not attempt[0]:
            continue
        mapping = mapping_options(pycolmap, settings, len(names), *attempt)
        say("pose: mapping%s", " (two-view tracks kept)" if attempt[0] else "")
        if sparse_raw.exists():
            shutil.rmtree(sparse_raw)
        sparse_raw.mkdir(parents=True)
        counter["n"] = 0
        models = pycolmap.incremental_mapping(database, raw_images, sparse_raw,
                                              options=mapping,
                                              next_image_callback=registered_one)
        best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
        if best is not None and best.num_reg_images() >= 2:
            break
    registered = sorted(best.images[i].name for i in best.reg_image_ids()) if best else []
    if len(registered) < 2:
        reasons = why_unregistered(database, names, set(registered))
        raise ValueError(f"COLMAP registered {len(registered)} of {len(names)} photos (two are "
                         "needed): " + "; ".join(reasons) + ". Photos of one scene that "
                         "overlap, with texture and a baseline (not a rotation only) register; "
                         "more photos between these help")
    if len(models) > 1:
        log.warning("pose: COLMAP made %d separate models; keeping the largest (%d photos); "
                    "the others' photos are not posed", len(models), len(registered))
    # the chosen model as sparse/0, the others removed (COLMAP numbers them 0, 1, ...)
    final_raw = work / "sparse0"
    if final_raw.exists():
        shutil.rmtree(final_raw)
    final_raw.mkdir()
    best.write_binary(str(final_raw))
    shutil.rmtree(sparse_raw)
    sparse_raw.mkdir()
    final_raw.rename(sparse_raw / "0")

    say("pose: undistorting to a PINHOLE camera")
    for stale in (out / "images", out / "sparse"):
        if stale.exists():
            shutil.rmtree(stale)
    pycolmap.undistort_images(out, sparse_raw / "0", raw_images, num_threads=settings.threads)
    for extra in ("stereo", "run-colmap-geometric.sh", "run-colmap-photometric.sh"):
        p = out / extra  # COLMAP's dense-stereo scaffolding, not used here
        if p.is_dir():
            shutil.rmtree(p)
        elif p.is_file():
            p.unlink()
    shutil.rmtree(raw_images)  # the links or copies: the originals stay where they were
    result = PoseResult(model=out / "sparse", images=out / "images", registered=registered,
                        unregistered=sorted(set(names) - set(registered)),
                        mean_reprojection_error=float(best.compute_mean_reprojection_error()),
                        points=int(best.num_points3D()), camera_mode=mode, matching=matching,
                        seconds=time.perf_counter() - t0)
    if result.unregistered:
        log.warning("pose: %d photo(s) did not register: %s", len(result.unregistered),
                    "; ".join(why_unregistered(database, names, set(registered))))
    write_json(out / "pose.json", {
        "settings": asdict(settings), "photos": [str(p) for p in paths],
        "photo_sha256": photo_hashes(paths),
        **{k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(result).items()},
        "pycolmap": getattr(pycolmap, "__version__", "?")})
    return result


def photo_hashes(photos: list[Path]) -> list[str]:
    """The sha256 of each photo's bytes (what ``posed_before`` compares)."""
    return [sha256(p, "photo", MAX_PHOTO_BYTES) for p in photos]


def posed_before(photos: list[Path], out: str | os.PathLike) -> PoseResult | None:
    """The ``PoseResult`` that ``pose_photos`` wrote into ``out`` for these very photos (the
    same bytes, in the same order), or None (never posed there, other photos, or a model
    removed since)."""
    record_file = Path(out) / "pose.json"
    if not record_file.is_file():
        return None
    try:
        record = json.loads(record_file.read_text())
        same = record.get("photo_sha256") == photo_hashes([Path(p) for p in photos])
    except (ValueError, OSError):
        return None
    if not same or not (Path(out) / "sparse" / "images.bin").is_file():
        return None
    fields = {k: record[k] for k in PoseResult.__dataclass_fields__}
    fields["model"], fields["images"] = Path(fields["model"]), Path(fields["images"])
    return PoseResult(**fields)


def default_pose_folder(photos: list[str | os.PathLike]) -> Path:
    """``outputs/pose/photos_<hash>``: where ``render``/``view`` pose a user's photos when no
    folder is named, one per set of photos (their hashes')."""
    digest = hashlib.sha256("".join(photo_hashes([Path(p) for p in photos])).encode())
    return Path("outputs") / "pose" / f"photos_{digest.hexdigest()[:12]}"


def similarity_align(source: np.ndarray, target: np.ndarray
                     ) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (scale s, rotation R, translation t) minimising
    ``sum |s R source_i + t - target_i|^2`` over corresponding points [N, 3] (Umeyama 1991,
    eqs. 34-42; N >= 3 not all on a line).

    Examples:
        >>> src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> s, r, t = similarity_align(src, 2 * src + 1)
        >>> round(s, 6), np.allclose(r, np.eye(3)), t.round(6).tolist()
        (2.0, True, [1.0, 1.0, 1.0])
    """
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0  # a reflection is not a rotation
    r = u @ sign @ vt
    var_s = (xs ** 2).sum() / len(source)
    s = float(np.trace(np.diag(d) @ sign) / var_s)
    return s, r, mu_t - s * r @ mu_s

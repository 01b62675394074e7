"""What the node's compressed transports cost and save on a real frame (2026-11-24).

The Motorcycle pair of scikit-image at 640×480 through the node's pipeline (Census-BM, PKRN —
the outputs' content, not the confidence method, sets what compression achieves — D = 128,
threshold 0.5), then the node's own encoders: ``confidence_overlay`` raw vs JPEG at several
qualities, ``depth`` raw vs ``compressedDepth`` at several PNG levels, both encodings, with
the geometry of the Middlebury 2014 calibration scaled to 640 px. Median of ``--repeat`` runs.

    python docs/measurements/2026-11-24_compressed/compressed.py --repeat 20
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from skimage import data
from std_msgs.msg import Header

from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline
from cva_confidence_ros.plots import confidence_overlay
from cva_confidence_ros.pointcloud import StereoGeometry, disparity_to_depth
from cva_confidence_ros.ros.convert import depth_to_image, rgb_to_image
from cva_confidence_ros.ros.transport import (
    compressed_depth_to_array,
    depth_image_to_compressed_depth,
    rgb_to_compressed,
)


def _median_ms(call, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        tic = time.perf_counter()
        call()
        times.append((time.perf_counter() - tic) * 1e3)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=20)
    args = parser.parse_args()
    left, right, _ = data.stereo_motorcycle()
    factor = left.shape[1] / 640
    import cv2

    size = (640, round(left.shape[0] / factor))
    left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
    right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    pipeline = StereoPipeline(
        PipelineConfig(matcher='census_bm', confidence_method='pkrn', max_disparity=128)
    )
    result = pipeline.process(left, right)
    confidence = np.clip(np.nan_to_num(result.confidence), 0, 1)
    # Middlebury 2014 Motorcycle (calib.txt): f = 3979.911 px, cx 1244.772 / 1369.115 px,
    # cy 1019.507 px, baseline 193.001 mm, at 2964 px wide.
    geometry = StereoGeometry(
        fx=3979.911 / factor, fy=3979.911 / factor, cx=1244.772 / factor,
        cy=1019.507 / factor, cx_right=1369.115 / factor, baseline=0.193001,
    )
    header = Header(frame_id='left_optical')
    print(f'{size[0]}×{size[1]} px, kept {result.valid.mean():.3f} of the pixels')
    overlay = confidence_overlay(result.left, confidence, result.valid)
    raw = rgb_to_image(overlay, header)
    print('\n| confidence_overlay | bytes | × raw | encode ms | mean abs error (0-255) |')
    print('|---|---:|---:|---:|---:|')
    print(f'| raw rgb8 | {len(raw.data):,} | 1 | – | 0 |')
    for quality in (95, 80, 50):
        msg = rgb_to_compressed(overlay, header, jpeg_quality=quality)
        decoded = cv2.cvtColor(
            cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR),
            cv2.COLOR_BGR2RGB,
        )
        ms = _median_ms(lambda q=quality: rgb_to_compressed(overlay, header, jpeg_quality=q),
                        args.repeat)
        error = np.abs(decoded.astype(int) - overlay).mean()
        print(f'| JPEG {quality} | {len(msg.data):,} | {len(raw.data) / len(msg.data):.0f}× '
              f'smaller | {ms:.1f} | {error:.2f} |')
    depth = disparity_to_depth(result.disparity, geometry, result.valid)
    print(f'\ndepth of the kept pixels: {np.nanmin(depth):.2f} to {np.nanmax(depth):.2f} m')
    print('\n| depth | bytes | × raw | encode ms | max error of the sent depths |')
    print('|---|---:|---:|---:|---:|')
    for encoding in ('32FC1', '16UC1'):
        image = depth_to_image(depth, header, encoding)
        print(f'| raw {encoding} | {len(image.data):,} | 1 | – | 0 |')
        for level in (9, 3, 1):
            msg = depth_image_to_compressed_depth(image, png_level=level)
            back = compressed_depth_to_array(msg)
            sent = np.isfinite(back)
            error = np.abs(back[sent] - depth[sent]).max()
            ms = _median_ms(lambda im=image, lv=level: depth_image_to_compressed_depth(
                im, png_level=lv), args.repeat)
            print(f'| compressedDepth {encoding}, PNG level {level} | {len(msg.data):,} | '
                  f'{len(image.data) / len(msg.data):.1f}× smaller | {ms:.1f} | '
                  f'{1000 * error:.2f} mm |')


if __name__ == '__main__':
    main()

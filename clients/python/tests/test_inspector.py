"""The loop inspector in a real browser: Debian's chromium and chromium-driver driven by PyPI
selenium 4.51.0 (pointed at Debian's driver, so it downloads nothing), against a real `loopd serve`
(TLS, a tenant key typed into the page). After the desk frames (slambook2, live frames with
geometric verification) and the corridor (a bag through `loopd ingest --thumbnails`) the page lists
exactly the kept loops, the known revisits among them; both thumbnails of a loop load and a
verified loop's inlier matches are drawn; the score slider hides the loops below it. A loop
rejected on the page (KITTI 00's poses, where accepted loops are pose-graph edges) is marked
rejected in the export's loops.csv and is gone from its graph.g2o. Screenshots are saved in
target/inspector/ for a person to look at."""
from __future__ import annotations

import io
import json
import os
import tarfile
import urllib.request

import bagmaker
import numpy as np
import pytest
import test_export_kitti as kitti
from conftest import BIN, DATA, REPO, corridor_truth
from test_bags import ingest

from loopd_client import Client, Frame, query_options

from selenium import webdriver
from selenium.webdriver.chrome.options import Options
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

SHOTS = REPO / "target/inspector"
DESK = [DATA / f"slambook2-ch11/{i}.png" for i in range(1, 11)]
CORRIDOR = sorted((DATA / "corridor/ref").glob("*.jpg")) + sorted((DATA / "corridor/query").glob("*.jpg"))


@pytest.fixture(scope="module")
def key(server):
    k = server.tenant("inspector")
    # `loopd ingest` (test_bags.ingest) reads the key from here.
    (server.root / "bags.key").write_text(k)
    return k


@pytest.fixture(scope="module")
def browser():
    os.environ["SE_OFFLINE"] = "true"  # Selenium Manager must not look for drivers online
    options = Options()
    options.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1500,1250",
                "--ignore-certificate-errors"):  # the test server's CA is made at run time
        options.add_argument(arg)
    options.set_capability("acceptInsecureCerts", True)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    yield driver
    driver.quit()


def open_inspector(driver, server, key, session):
    """The session's page, loaded with the key typed in; the page's status line."""
    driver.get(f"https://127.0.0.1:{server.http_port}/v1/sessions/{session}/inspect")
    field = driver.find_element(By.ID, "key")
    field.clear()
    field.send_keys(key)
    driver.find_element(By.ID, "load").click()
    body = driver.find_element(By.TAG_NAME, "body")
    WebDriverWait(driver, 120).until(lambda d: body.get_attribute("data-loaded") in ("true", "error"))
    status = driver.find_element(By.ID, "status").text
    assert body.get_attribute("data-loaded") == "true", status
    return status


def shown_loops(driver, visible_only=False):
    rows = driver.find_elements(By.CSS_SELECTOR, "#loops tr.loop-row")
    return {(int(r.get_attribute("data-q")), int(r.get_attribute("data-m"))) for r in rows
            if not visible_only or "hidden" not in r.get_attribute("class").split()}


def select(driver, q, m):
    """Clicks loop q -> m in the table and waits for its detail to be drawn."""
    row = driver.find_element(By.CSS_SELECTOR, f'#loops tr.loop-row[data-q="{q}"][data-m="{m}"]')
    driver.execute_script("arguments[0].scrollIntoView()", row)
    row.click()
    canvas = driver.find_element(By.ID, "inliers")
    WebDriverWait(driver, 30).until(lambda d: canvas.get_attribute("data-lines") not in (None, ""))
    assert driver.find_element(By.ID, "detail-title").text == f"{q} → {m}"
    return int(canvas.get_attribute("data-lines"))


def show_all(driver):
    """Turns the page's "only loops" switch off: every kept candidate is listed and can be chosen."""
    box = driver.find_element(By.ID, "only-loops")
    if box.is_selected():
        box.click()
    assert not box.is_selected()


def thumbnail_widths(driver):
    return [driver.execute_script("return arguments[0].naturalWidth", driver.find_element(By.ID, i))
            for i in ("thumb-query", "thumb-match")]


def screenshot(driver, name):
    driver.execute_script("window.scrollTo(0, 0)")
    SHOTS.mkdir(parents=True, exist_ok=True)
    path = SHOTS / f"{name}.png"
    driver.save_screenshot(str(path))
    print(f"screenshot: {path}")


def export(server, key, session, tmp):
    request = urllib.request.Request(f"https://127.0.0.1:{server.http_port}/v1/sessions/{session}/export",
                                     headers={"Authorization": f"Bearer {key}"})
    with urllib.request.urlopen(request, context=server.ssl) as r:
        tarfile.open(fileobj=io.BytesIO(r.read())).extractall(tmp, filter="data")
    return (tmp / "loops.csv").read_text().splitlines(), (tmp / "graph.g2o").read_text().splitlines()


def info(server, key):
    request = urllib.request.Request(f"https://127.0.0.1:{server.http_port}/v1/info",
                                     headers={"Authorization": f"Bearer {key}"})
    with urllib.request.urlopen(request, context=server.ssl) as r:
        return json.load(r)


def test_desk_loops_thumbnails_inliers_and_slider(server, key, browser):
    with Client(server.grpc, key=key, ca=server.ca) as c:
        c.create_session("desk", thumbnails=True)
        options = query_options(k=3, verify=True)
        for i, path in enumerate(DESK):
            c.add_and_query("desk", "desk", Frame(image=path.read_bytes(), timestamp=float(i), frame_id=i), options)
        kept = {(l.query_frame, l.match_frame): l for l in c.loops("desk")}
    assert (9, 0) in kept and kept[(9, 0)].verified, "the desk revisit 10.png -> 1.png is kept, verified"

    status = open_inspector(browser, server, key, "desk")
    assert f"10 frames of 1 robot(s), {len(kept)} kept loops" in status, status
    assert shown_loops(browser) == set(kept), "the page lists exactly the kept loops"
    edges = browser.find_elements(By.CSS_SELECTOR, "#map .loop")
    assert {(int(e.get_attribute("data-q")), int(e.get_attribute("data-m"))) for e in edges} == set(kept)
    assert browser.find_element(By.ID, "similarity").get_attribute("data-size") == "10"

    lines = select(browser, 9, 0)
    assert thumbnail_widths(browser) == [160, 160], "both thumbnails load (160 px wide)"
    assert lines == min(100, kept[(9, 0)].inliers) > 0, "the inlier matches are drawn"
    screenshot(browser, "desk")

    # It opens showing only the loops: candidates whose confidence reaches the server's loop
    # confidence (/v1/info); the switch shows every kept candidate.
    loop_confidence = info(server, key)["loop_confidence"]
    loops = {p for p, l in kept.items() if l.HasField("confidence") and l.confidence >= loop_confidence}
    assert (9, 0) in loops and len(loops) < len(kept), (loops, loop_confidence)
    assert shown_loops(browser, visible_only=True) == loops
    assert len(browser.find_elements(By.CSS_SELECTOR, "#map .loop.hidden")) == len(kept) - len(loops)
    browser.find_element(By.ID, "only-loops").click()
    assert shown_loops(browser, visible_only=True) == set(kept)

    # The slider hides the loops scoring below it, in the table and on the map.
    threshold = kept[(9, 0)].score + 1e-3
    browser.execute_script("const s = document.getElementById('threshold'); s.value = arguments[0];"
                           "s.dispatchEvent(new Event('input'))", f"{threshold:.3f}")
    set_to = float(browser.find_element(By.ID, "threshold").get_attribute("value"))
    above = {p for p, l in kept.items() if l.score >= set_to}
    assert shown_loops(browser, visible_only=True) == above and (9, 0) not in above
    hidden = browser.find_elements(By.CSS_SELECTOR, "#map .loop.hidden")
    assert len(hidden) == len(kept) - len(above)


def test_corridor_bag_shows_the_known_revisits(server, key, browser, tmp_path):
    frames = [(p, 1_700_000_000.0 + 0.1 * i) for i, p in enumerate(CORRIDOR)]
    bag = bagmaker.write_mcap(tmp_path / "corridor", frames, "/mapper/cam/image_raw/compressed", "compressed")
    job = ingest(server, bag, "--session", "corridor", "--thumbnails")
    assert (job["state"], job["done"], job["errors"]) == ("done", 222, []), job
    with Client(server.grpc, key=key, ca=server.ca) as c:
        records = {(l.query_frame, l.match_frame): l for l in c.loops("corridor")}
    kept = set(records)
    n = len(CORRIDOR) // 2
    truth = corridor_truth()
    known = {(q, m) for q, m in kept if q >= n and m < n and m in truth.get(q - n, set())}
    assert len(known) >= 10, f"{len(known)} of {len(kept)} kept loops are corridor revisits (gt.csv)"

    status = open_inspector(browser, server, key, "corridor")
    assert f"222 frames of 1 robot(s), {len(kept)} kept loops" in status, status
    assert shown_loops(browser) == kept, "the page lists exactly the kept loops, the known revisits among them"
    # It opens on what the server's loop confidence accepts of the job's candidates; then all.
    loop_confidence = info(server, key)["loop_confidence"]
    loops = {p for p, l in records.items() if l.HasField("confidence") and l.confidence >= loop_confidence}
    assert shown_loops(browser, visible_only=True) == loops
    show_all(browser)
    assert shown_loops(browser, visible_only=True) == kept
    q, m = min(known)
    first = records[(q, m)]
    drawn = min(100, first.inliers) if first.verified else 0
    assert select(browser, q, m) == drawn, "inlier matches drawn for a verified loop only"
    assert thumbnail_widths(browser) == [160, 160], "both thumbnails load"
    screenshot(browser, "corridor")
    print(f"corridor: {len(kept)} kept candidates, {len(loops)} at the loop confidence, {len(known)} revisits in gt.csv")


def test_a_loop_rejected_on_the_page_leaves_the_graph(server, key, browser, tmp_path):
    stamps, true = kitti.kitti_poses()
    odometry = kitti.drifted(true)
    with Client(server.grpc, key=key, ca=server.ca) as c:
        dim = c.create_session("kitti00").dim
        descriptors = kitti.place_descriptors(true, dim)
        options = query_options(k=1, verify=False, exclude_last_seconds=60.0, min_score=0.6)
        for i, (t, T) in enumerate(zip(stamps, odometry)):
            c.add_and_query("kitti00", "car", Frame(descriptor=descriptors[i].tolist(), timestamp=float(t),
                                                    frame_id=i, pose=kitti.pose_msg(T)), options)
        loops = [(l.query_frame, l.match_frame) for l in c.loops("kitti00")]
        accepted = [(q, m) for q, m in loops if np.linalg.norm(true[q][:3, 3] - true[m][:3, 3]) < 5.0]
        for q, m in accepted:
            c.set_verdict("kitti00", q, m, True, relative_pose=kitti.relative(true[q], true[m]))
    assert len(accepted) >= 30
    q, m = accepted[len(accepted) // 2]
    _, graph = export(server, key, "kitti00", tmp_path / "before")
    assert any(line.startswith(f"EDGE_SE3:QUAT {q} {m} ") for line in graph), "an accepted loop is an edge"

    status = open_inspector(browser, server, key, "kitti00")
    assert f"{len(true)} frames of 1 robot(s), {len(loops)} kept loops" in status, status
    trajectory = browser.find_element(By.CSS_SELECTOR, "#map .trajectory")
    assert trajectory.get_attribute("data-points") == str(len(true)), "the trajectory from the poses"
    assert len(browser.find_elements(By.CSS_SELECTOR, "#map .loop")) == len(loops)
    show_all(browser)
    select(browser, q, m)
    browser.find_element(By.ID, "reject").click()
    WebDriverWait(browser, 30).until(lambda d: "saved" in d.find_element(By.ID, "verdict-status").text)
    assert browser.find_element(By.ID, "verdict-status").text == "rejected (saved)"
    row = browser.find_element(By.CSS_SELECTOR, f'#loops tr.loop-row[data-q="{q}"][data-m="{m}"]')
    assert "rejected" in row.get_attribute("class").split()
    screenshot(browser, "kitti00")

    loops_csv, graph = export(server, key, "kitti00", tmp_path / "after")
    row = [line for line in loops_csv if line.startswith(f"{q},{m},")]
    assert len(row) == 1 and ",rejected," in row[0], row
    assert sum(",accepted," in line for line in loops_csv) == len(accepted) - 1
    assert not any(line.startswith(f"EDGE_SE3:QUAT {q} {m} ") for line in graph), "gone from graph.g2o"
    assert sum(line.startswith("EDGE_SE3:QUAT") for line in graph) == len(true) - 1 + len(accepted) - 1


def test_a_metric_loop_shows_its_transform_in_metres_and_its_sigma(server, key, browser):
    """tum-desk frames sent with their depth: the page gives a metric loop's translation in metres
    and the standard deviations of its covariance; a monocular session's loop says its scale is
    unknown."""
    desk = DATA / "rgbd-slambook2/tum-desk"
    with Client(server.grpc, key=key, ca=server.ca) as c:
        for name, depth in (("rgbd-page", True), ("mono-page", False)):
            c.create_session(name, camera=[518.0, 519.0, 325.5, 253.5])
            for i in range(1, 6):
                frame = Frame(image=(desk / f"color/{i}.png").read_bytes(), timestamp=float(i), frame_id=i,
                              depth=(desk / f"depth/{i}.pgm").read_bytes() if depth else None)
                c.add_and_query(name, "cam", frame, query_options(k=1, exclude_last_frames=0))
        metric = [l for l in c.loops("rgbd-page") if l.metric]
        mono = [l for l in c.loops("mono-page") if l.verified and l.HasField("relative_pose")]
    assert metric and mono, (metric, mono)
    facts = lambda: browser.find_element(By.ID, "facts").text  # noqa: E731
    open_inspector(browser, server, key, "rgbd-page")
    show_all(browser)
    select(browser, metric[0].query_frame, metric[0].match_frame)
    text = facts()
    t = metric[0].relative_pose
    assert f"{(t.tx ** 2 + t.ty ** 2 + t.tz ** 2) ** 0.5:.3f} m" in text, text
    assert "σ" in text and " cm · rotation " in text, text
    open_inspector(browser, server, key, "mono-page")
    show_all(browser)
    select(browser, mono[0].query_frame, mono[0].match_frame)
    assert "scale unknown" in facts(), facts()

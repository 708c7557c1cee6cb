"""The web client's own behaviour in headless Chromium, fed by a display server in this process (no ROS, no node):
the page runs under its Content-Security-Policy with no violation (its modules, worker and lil-gui's styles as a
file), the panel is lil-gui's, and what leaves the scene leaves the page - a removed mesh's geometry and material
are disposed, a departing agent's panel row goes, and another agent keeps its garments' swatches."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from .test_viewer import browser, pytestmark  # noqa: F401 (Chromium through Playwright, skipped without either)

from agentdress_ros.viewer.state import DisplayScene
from agentdress_ros.viewer.server import DisplayServer, NpmMissing, web_root

PHENOTYPES = ["gender", "age", "muscle", "weight", "height", "proportions"]
AGENTS = ("node/agent_000", "node/agent_001")
GARMENTS = ("tshirt", "trousers")


def _web() -> Path:
    try:
        return web_root()
    except NpmMissing as error:
        pytest.skip(str(error))


def _add_agent(scene: DisplayScene, agent: str):
    rng = np.random.default_rng(len(agent))
    for garment in GARMENTS:  # two triangles each: what the page draws does not matter here
        scene.set_mesh(agent, garment, rng.normal(size=(6, 3)).astype(np.float32), np.array([[0, 1, 2], [3, 4, 5]]))


@pytest.fixture
def page(browser):
    """(scene, page, messages): two agents with two garments each, the page open on them; `messages` collects the
    page's errors and every console line about the security policy."""
    scene = DisplayScene()
    for agent in AGENTS:
        _add_agent(scene, agent)
    server = DisplayServer(scene, _web(), "127.0.0.1", 0, phenotypes=PHENOTYPES)
    server.start()
    context = browser.new_context(viewport={"width": 800, "height": 600})
    page = context.new_page()
    messages = []
    page.on("pageerror", lambda error: messages.append(str(error)))
    page.on("console", lambda message: messages.append(message.text)
            if "Content Security Policy" in message.text or message.type == "error" else None)
    try:
        page.goto(server.url(), timeout=120_000)
        # conditions as functions: Playwright evaluates a bare expression with eval, which the policy forbids
        page.wait_for_function("() => window.agentdress && agentdress.connected && "
                               f"Object.keys(agentdress.meshes).length === {len(AGENTS) * len(GARMENTS)} && "
                               f"document.querySelectorAll('#agents .swatch').length === {len(AGENTS) * len(GARMENTS)}",
                               timeout=120_000)
        yield scene, page, messages
    finally:
        context.close()
        server.stop()


def _swatches(page) -> dict:
    return page.evaluate("""() => Object.fromEntries([...document.querySelectorAll('#agents [data-agent]')].map(
        (row) => [row.dataset.agent, [...row.querySelectorAll('.swatch')].map((s) => s.style.background)]))""")


def test_the_page_runs_under_its_policy_with_lil_gui_styled_from_a_file(page):
    _, page, messages = page
    panel = page.evaluate("""() => {
        const panel = document.getElementById('panel');
        const sheets = [...document.styleSheets].map((s) => (s.href || 'inline').split('/').pop());
        return {lilGui: panel.classList.contains('lil-gui'), sheets, styles: document.querySelectorAll('style').length,
                background: getComputedStyle(panel).getPropertyValue('--background-color').trim(),
                sliders: [...document.querySelectorAll('#sliders input')].map((i) => i.name),
                choices: [...document.querySelectorAll('#sliders select option')].map((o) => o.textContent)};
    }""")
    assert panel["lilGui"] and panel["background"] == "#1f1f1f", panel  # lil-gui's own styles reached the panel
    assert panel["sheets"] == ["lil-gui.css", "style.css"] and panel["styles"] == 0, panel  # none injected
    assert panel["sliders"] == PHENOTYPES and panel["choices"] == list(AGENTS), panel
    assert not messages, messages


def test_removing_a_mesh_disposes_its_geometry_and_material(page):
    scene, page, messages = page
    page.evaluate(f"""() => {{
        window.disposed = [];
        for (const mesh of agentdress.world.children.filter((m) => m.name.startsWith('{AGENTS[1]}/'))) {{
            mesh.geometry.addEventListener('dispose', () => disposed.push('geometry ' + mesh.name));
            mesh.material.addEventListener('dispose', () => disposed.push('material ' + mesh.name));
        }}
    }}""")
    scene.remove_agent(AGENTS[1])
    page.wait_for_function("() => window.disposed.length === 4", timeout=30_000)
    assert sorted(page.evaluate("window.disposed")) == sorted(
        f"{part} {AGENTS[1]}/{garment}" for part in ("geometry", "material") for garment in GARMENTS)
    assert sorted(page.evaluate("agentdress.world.children.map((m) => m.name)")) == sorted(
        f"{AGENTS[0]}/{garment}" for garment in GARMENTS)
    assert not messages, messages


def test_a_departing_agent_leaves_the_panel_and_the_others_keep_their_swatches(page):
    scene, page, messages = page
    before = _swatches(page)
    assert set(before) == set(AGENTS) and all(len(s) == len(GARMENTS) for s in before.values()), before
    scene.remove_agent(AGENTS[1])
    page.wait_for_function(f"() => !document.querySelector('#agents [data-agent=\"{AGENTS[1]}\"]')", timeout=30_000)
    page.wait_for_timeout(600)  # two refreshes of the rows (every 250 ms)
    assert _swatches(page) == {AGENTS[0]: before[AGENTS[0]]}  # both of its garments' colours are still there
    choices = page.evaluate("[...document.querySelectorAll('#sliders select option')].map((o) => o.textContent)")
    assert choices == [AGENTS[0]]
    _add_agent(scene, AGENTS[1])  # and it comes back
    page.wait_for_function(f"() => document.querySelectorAll('#agents [data-agent=\"{AGENTS[1]}\"] .swatch')"
                           f".length === {len(GARMENTS)}", timeout=30_000)
    assert not messages, messages

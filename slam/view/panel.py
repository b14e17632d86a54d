"""The viewer's metrics panel: a run's metrics.json (slam.run.sequence / slam.run.team_results keys) as Markdown."""

from __future__ import annotations

from .scene import AGENT_COLORS, LOOP_COLORS

_COLOR_NAMES = dict(zip(AGENT_COLORS, ["blue", "green", "red", "purple", "cyan", "brown", "olive", "grey"]))
_LOOP_NAMES = {"intra": "orange", "inter": "magenta"}


def _cm(x) -> str:
    return "–" if x is None else f"{100 * float(x):.2f}"


def _f(x, fmt: str = "{:.2f}") -> str:
    return "–" if x is None else fmt.format(float(x))


def metrics_markdown(m: dict, names: list[str], scene=None) -> str:
    """Markdown for a team (m["agents"]) or one agent (m["agent"]); `scene` adds its legend and notes."""
    from .scene import agent_color

    lines = []
    if "agents" in m:
        lines += ["| agent | colour | ATE [cm] | no LC [cm] | PSNR [dB] | frames |", "|---|---|--:|--:|--:|--:|"]
        for i, a in enumerate(m["agents"]):
            frame = "" if a.get("in_global_frame", True) else " (own frame)"
            lines.append(f"| {a.get('name')}{frame} | {_COLOR_NAMES.get(agent_color(i), '')} | "
                         f"{_cm(a.get('ate_rmse'))} | {_cm(a.get('ate_rmse_no_lc'))} | {_f(a.get('psnr'))} | "
                         f"{a.get('frames_tracked', a.get('frames', '–'))} |")
        loops = m.get("loops") or {}
        li, lx = loops.get("intra") or {}, loops.get("inter") or {}
        wall = (m.get("time_s") or {}).get("wall")
        lines += ["", f"**team ATE** {_cm(m.get('ate_rmse_team'))} cm (one alignment)  ",
                  f"**PSNR** {_f(m.get('psnr'))} dB keyframes, {_f(m.get('psnr_novel'))} dB held out "
                  f"(before refinement {_f(m.get('psnr_before_refine'))})  ",
                  f"**SSIM** {_f(m.get('ssim'), '{:.3f}')}, **depth L1** {_cm(m.get('depth_l1'))} cm  ",
                  f"**loops** intra {li.get('accepted', 0)}/{li.get('candidates', 0)}, "
                  f"inter {lx.get('accepted', 0)}/{lx.get('candidates', 0)} accepted/candidates  ",
                  f"**Gaussians** {m.get('gaussians', '–')}, **wall** {_f(wall, '{:.0f}')} s"]
    else:
        t = (m.get("time_s") or {}).get("total")
        lines += [f"**{m.get('agent', names[0])}** ({_COLOR_NAMES.get(agent_color(0), '')}): "
                  f"{m.get('frames', '–')} frames, {m.get('keyframes', '–')} keyframes, {m.get('submaps', '–')} submaps  ",
                  f"**ATE** {_cm(m.get('ate_rmse'))} cm  ",
                  f"**PSNR** {_f(m.get('psnr'))} dB, **SSIM** {_f(m.get('ssim'), '{:.3f}')}, "
                  f"**depth L1** {_cm(m.get('depth_l1'))} cm  ",
                  f"**loops** {m.get('loops_accepted', 0)} accepted of {m.get('loop_candidates', 0)} candidates  ",
                  f"**Gaussians** {m.get('gaussians', '–')}, **{_f(m.get('fps'))} fps**, wall {_f(t, '{:.0f}')} s"]
    lines += ["", "Lines: solid colour = with loop closures, pale = tracking only, dark grey = ground truth; "
              f"loop edges: {_LOOP_NAMES['intra']} = intra-agent, {_LOOP_NAMES['inter']} = inter-agent."]
    if scene is not None:
        s = scene.summary()
        lines += ["", f"Shown: {s['gaussians']} Gaussians ({', '.join(s['maps'])}), {s['keyframes']} keyframes, "
                      f"{s['loops'].get('intra', 0)} intra / {s['loops'].get('inter', 0)} inter loop edges."]
        lines += [f"- {n}" for n in scene.notes]
    return "\n".join(lines)

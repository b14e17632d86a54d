"""`swarmsplat bag-info BAG`: a bag's topics with their types, message counts and rates, and what a run would
take from it."""

from __future__ import annotations

from pathlib import Path

from swarmsplat.kernels.errors import InputError

from .sequence import open_reader
from .topics import agent_namespaces, choose_topics

ONE_AGENT = "(one agent)"


def bag_info(path: str | Path) -> dict:
    """{"path", "format", "duration_s", "messages", "topics": [{"topic", "type", "count", "rate_hz"}, ...],
    "agents": {namespace or "": chosen topics, or "error": why none}}."""
    path = Path(path)
    reader = open_reader(path)
    try:
        dur = reader.duration * 1e-9
        topics = []
        for name, info in sorted(reader.topics.items()):
            count = int(info.msgcount)
            conns = [c for c in reader.connections if c.topic == name]
            rate = (count - 1) / dur if dur > 0 and count > 1 else None
            topics.append({"topic": name, "type": info.msgtype, "count": count,
                           "rate_hz": round(rate, 2) if rate else None, "connections": len(conns)})
        types = {t["topic"]: t["type"] for t in topics}
        agents: dict = {}
        try:
            for ns in agent_namespaces(types, None):
                agents[ns or ONE_AGENT] = choose_topics(types, None, str(path), namespace=ns).as_dict()
        except InputError as e:
            agents = {"error": str(e)}
        fmt = "ros1" if path.suffix == ".bag" else "mcap" if path.suffix == ".mcap" or any(
            p.suffix == ".mcap" for p in (path.iterdir() if path.is_dir() else [])) else "ros2"
        return {"path": str(path), "format": fmt, "duration_s": round(dur, 3),
                "messages": int(reader.message_count), "topics": topics, "agents": agents}
    finally:
        reader.close()


def format_info(info: dict) -> str:
    rows = [f"{info['path']}: {info['format']}, {info['duration_s']:.1f} s, {info['messages']} messages", ""]
    w = max([len(t["topic"]) for t in info["topics"]] + [5])
    wt = max([len(t["type"] or "?") for t in info["topics"]] + [4])
    rows.append(f"{'topic':<{w}}  {'type':<{wt}}  {'count':>7}  {'rate':>8}   (rate: messages over the bag's duration)")
    for t in info["topics"]:
        rate = f"{t['rate_hz']:.2f} Hz" if t["rate_hz"] else "-"
        rows.append(f"{t['topic']:<{w}}  {t['type'] or '?':<{wt}}  {t['count']:>7}  {rate:>8}")
    rows.append("")
    if "error" in info["agents"]:
        rows.append(f"topics for a run: {info['agents']['error']}")
    else:
        for agent, chosen in info["agents"].items():
            who = "" if agent == ONE_AGENT else f" (agent {agent.strip('/')})"
            rows.append(f"a run takes{who}: " + ", ".join(f"{k} {v}" for k, v in chosen.items()))
    return "\n".join(rows)

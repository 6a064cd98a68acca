"""The study scripts' ``--seeds`` argument: "0-11", "3", "0-3,8,10-11" as a list of ints."""


def seed_list(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out

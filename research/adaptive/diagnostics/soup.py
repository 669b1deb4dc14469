import copy
import sys

import torch

out, ins = sys.argv[1], sys.argv[2:]
cs = [torch.load(p, map_location="cpu", weights_only=False) for p in ins]
o = copy.deepcopy(cs[-1])
for k in o["state_dict"]:
    o["state_dict"][k] = (
        sum(c["state_dict"][k].double() for c in cs).div(len(cs)).to(o["state_dict"][k].dtype)
    )
torch.save(o, out)

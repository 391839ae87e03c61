# ruff: noqa: E702
"""Leave-one-out on TRAINING rows only: forward accuracy of the local model (k, ridge, kernel)."""
import itertools
import json

import numpy as np

from invphys.plugins.baselines.local_linear import LocalLinear, local_fit

tr=np.load('runs/protocol_paper_lean/inverter/data/train.npz'); T,Y=tr['theta'],tr['y']
s=np.array(json.load(open('runs/protocol_paper_lean/invert/targets.json'))['scales'])
rng=np.random.default_rng(0); sub=rng.choice(len(T),400,replace=False)
res={}
for k,ridge,kern in itertools.product([10,12,15,20,25],[0.03,0.1,0.3,1.0],['uniform','gaussian']):
    p=LocalLinear(k=k,ridge=ridge,kernel=kern); p.fit(T,Y,s)
    idx,dist=p.neighbours(Y[sub],exclude=sub)
    r=[]
    for i,q in enumerate(sub):
        th,z=p._theta[idx[i]],p._z[idx[i]]
        w=np.exp(-0.5*(dist[i]/dist[i][-1])**2) if kern=='gaussian' else np.ones(k)
        w/=w.sum(); m=w@th; b,a=local_fit(th,z,m,w,ridge)
        r.append(np.exp(-3*np.sqrt(np.mean((b+a@(T[q]-m)-p._z[q])**2))))
    res[f'{k},{ridge},{kern}']=float(np.mean(r)); print(k,ridge,kern,f'{np.mean(r):.4f}',flush=True)
json.dump(res,open('.gpu/h2b/cv_forward2.json','w'),indent=1)

# ruff: noqa: E702
"""Diagnostic (rule fixed before looking): answer with NPE's best-of-64 instead of the lookup when the
residual-corrected ensemble scores it above the lookup row's real R. Uses the lean run's ensemble and
its memoised simulations of both answers (no new runs)."""
import json

import numpy as np

from invphys.core.objectives import recovery_reward
from invphys.plugins.baselines.nearest_neighbour import NearestNeighbour
from invphys.registry import default_registry

v=json.load(open('runs/protocol_paper_lean/validate/validation.json'))
tg=json.load(open('runs/protocol_paper_lean/invert/targets.json')); s=np.array(tg['scales']); Yt=np.array(tg['features'])
tr=np.load('runs/protocol_paper_lean/inverter/data/train.npz'); T,Y=tr['theta'],tr['y']
ens=default_registry().get('surrogate','ensemble').load('runs/protocol_paper_lean/train/surrogate')
by={(r['optimizer'],r['target_index']):r for r in v}
ks=sorted(k for (o,k) in by if o=='nearest_neighbour')
nn=NearestNeighbour(k=8); nn.fit(T,Y,s); idx,_=nn.neighbours(Yt[ks])
fr=np.asarray(ens.predict(T[idx].reshape(-1,9))).reshape(len(ks),8,-1); res=Y[idx]-fr
out={}
for h in [0.1,0.2]:
  for other in ['npe_surrogate','cma_penalised_nn','cma_es_540']:
    th=np.array([by[(other,k)]['theta'] for k in ks]); f=np.asarray(ens.predict(th))
    w=np.exp(-0.5*((th[:,None,:]-T[idx])**2).sum(-1)/h**2)+1e-300; w/=w.sum(1,keepdims=True)
    corr=f+np.einsum('bk,bkm->bm',w,res)
    sc=recovery_reward(corr,Yt[ks],s); sraw=recovery_reward(f,Yt[ks],s)
    nn_real=recovery_reward(Y[idx[:,0]],Yt[ks],s)
    ra_nn=np.array([by[('nearest_neighbour',k)]['r_actual'] for k in ks]); ra_o=np.array([by[(other,k)]['r_actual'] for k in ks])
    for name,score in [('corrected',sc),('raw',sraw)]:
        pick=score>nn_real; ra=np.where(pick,ra_o,ra_nn); d=ra-ra_nn
        rng=np.random.default_rng(0); bs=[d[rng.integers(0,len(d),len(d))].mean() for _ in range(2000)]
        print(f"h {h} {other:18s} {name:9s} switched {pick.sum():3d} R_actual {ra.mean():.3f} vs nn {ra_nn.mean():.3f} diff {d.mean():+.4f} [{np.percentile(bs,2.5):+.4f}, {np.percentile(bs,97.5):+.4f}]  oracle {np.maximum(ra_o,ra_nn).mean():.3f}")

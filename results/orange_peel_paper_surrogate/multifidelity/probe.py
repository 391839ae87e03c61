"""Multi-fidelity probe: does a quick-preset surrogate's prediction help the paper-preset surrogate?"""
import sys, time, numpy as np, torch
sys.path[:0]=['/work/main','/work/main/examples/orange_peel']
torch.set_num_threads(1)
from invphys.core.dataset import DatasetStore
from invphys.models.data import r2_scores
from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
from invphys.plugins.surrogates.mlp import MLPSurrogate
new = EnsembleSurrogate.Config().model_dump(include={"activation","batch_norm","dropout","optimizer","schedule","lr","max_epochs","patience"})
P = DatasetStore('/work/main/datasets/orange_peel_paper').arrays(ok_only=True)
Q = DatasetStore('/work/main/datasets/orange_peel_quick').arrays(ok_only=True)
n=len(P.theta); perm=np.random.default_rng(0).permutation(n)
te,tr=np.sort(perm[:round(.2*n)]),np.sort(perm[round(.2*n):])
names=list(P.feature_names)
def fit(X,Y,seed):
    m=MLPSurrogate(seed=seed,val_fraction=0.1,**new); m.fit(X,Y); return m
t0=time.time()
qs=[fit(Q.theta,Q.y,s) for s in range(3)]
qpred=lambda th: np.mean([m.predict(th) for m in qs],0)
print('quick surrogate trained', time.time()-t0, flush=True)
# how well does the quick model predict paper features (correlation per feature)
qp=qpred(P.theta)
print('corr(quick-pred, paper):', {k: round(float(np.corrcoef(qp[:,j],P.y[:,j])[0,1]),3) for j,k in enumerate(names)}, flush=True)
mu,sd=qp[tr].mean(0),qp[tr].std(0)
Xs=np.concatenate([P.theta,np.clip((qp-mu)/sd*0.15+0.5,0,1)],1)
for seed in range(2):
    for label,X in (('theta+quick',Xs),):
        m=fit(X[tr],P.y[tr],seed); r2,per=r2_scores(P.y[te],m.predict(X[te]))
        print(seed,label,round(r2,4),'min',round(min(per),3), {k:round(v,3) for k,v in zip(names,per)}, flush=True)

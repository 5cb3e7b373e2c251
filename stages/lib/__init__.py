"""stages/lib"""

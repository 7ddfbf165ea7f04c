"""ballbar.daemon"""
